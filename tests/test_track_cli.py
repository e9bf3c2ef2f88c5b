"""`jaxtrack track`, `eval` and `demo` on a tiny synthetic sequence, and the overlay drawing.

Most tests replace the tracker by `_FakeTracker`, which reports the ground truth with known errors
(frame 2 is turned by 15°, so it fails 5 cm / 5°): the CLI's checks, the CSV / frames.jsonl / overlay
writing and `eval` are exercised for real without compiling the step, and the errors `eval` prints
can be compared with the ones the fake put in. One test runs the real tracker end to end (region
only, 3 frames of 160x120).
"""

import json
import re
import time
import types
import typing

import cv2
import numpy as np
import pytest

import jaxtrack.track._sequence as sequence_module
from jaxtrack.cli import main, read_init_pose
from jaxtrack.geometry import make_transform, so3_exp
from jaxtrack.io import read_bop_results, read_sequence
from jaxtrack.track import OverlayWriter, overlay_frame
from jaxtrack.track._overlay import MODEL_COLOUR, SEGMENT_COLOUR, model_mask, segmentation_mask

W, H = 160, 120
TURN_DEG = {1: 0.5, 2: 15.0}  # the fake's rotation error per frame (frame 2 fails the 5° criterion)
STATUS = {1: "OK", 2: "LOST"}


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    from jaxtrack.synth import SynthConfig, write_sequence

    cfg = SynthConfig(object="box", appearance="photo", texture_photo="astronaut", size_mm=160, motion="random",
                      step_px=3, step_deg=1.5, frames=3, width=W, height=H, focal=175, background="coffee", seed=3)
    return write_sequence(cfg, tmp_path_factory.mktemp("track_cli") / "seq")


def _turn(deg):
    return make_transform(np.asarray(so3_exp(np.array([0.0, 0.0, np.radians(deg)]))), np.zeros(3))


class _FakeTracker:
    """Stands in for `Tracker`: reports the true world pose of each frame turned by TURN_DEG about the
    object's z axis (a pure rotation error), with the statuses in STATUS; records how it was built and started."""

    built: typing.ClassVar[list] = []
    truth = None  # callable frame index -> (4, 4) true world pose, set by the fixture

    def __init__(self, mesh, cameras, model=None, config=None, params=None, joint_limits=None, **options):
        self.cues, self.num_cameras, self.k, self.config = config.cues, cameras.K.shape[0], 0, config
        self.options = options  # pose_prior, late_rounds: passed only when given
        _FakeTracker.built.append(self)

    def start(self, frames, T_world_root, theta=None):
        self.starts = getattr(self, "starts", []) + [np.asarray(T_world_root, np.float64)]
        self.start_pose = self.starts[0]
        return types.SimpleNamespace(T_world_root=self.start_pose, theta=np.zeros(0))

    def step(self, state, frames):
        self.k += 1
        T = _FakeTracker.truth(self.k) @ _turn(TURN_DEG[self.k])
        phi = -np.ones((self.num_cameras, 40, 50))
        phi[:, 10:30, 10:40] = 1.0
        result = types.SimpleNamespace(
            T_world_root=T, theta=np.zeros(0), status=int(getattr(sequence_module.Status, STATUS[self.k])),
            confidence=0.9 if STATUS[self.k] == "OK" else 0.2, counts=np.full((self.num_cameras, len(self.cues)), 7), region_phi=phi,
        )
        info = {"timings": {"step_s": 0.001}, "offsets": np.tile([[20, 30]], (self.num_cameras, 1)), "crop_shape": (40, 50)}
        return types.SimpleNamespace(T_world_root=T, theta=np.zeros(0)), result, info

    def join_background(self):
        """`Tracker.join_background`: this stand-in compiles nothing in the background."""


def _world_truth(seq_dir):
    view = read_sequence(seq_dir).views[0]
    return lambda k: np.linalg.inv(view.T_cam_world) @ view.T_cam_obj[1][k]


@pytest.fixture
def fake(monkeypatch, seq_dir):
    _FakeTracker.built = []
    _FakeTracker.truth = staticmethod(_world_truth(seq_dir))
    monkeypatch.setattr(sequence_module, "Tracker", _FakeTracker)
    return _FakeTracker


def _video_frames(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            return frames
        frames.append(frame)


def test_track_writes_results_jsonl_and_video_and_eval_reads_them(seq_dir, fake, tmp_path, capsys):
    out, video = tmp_path / "res" / "run.csv", tmp_path / "overlay.mp4"
    assert main(["track", str(seq_dir), "-o", str(out), "--video", str(video), "--quiet", "--no-cache"]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and str(video) in printed and "LOST 1" in printed
    assert len(fake.built) == 1 and fake.built[0].cues == ("region", "flow", "sift")
    # The BOP CSV: frame 0 included (the starting pose), the fake's poses after it, in camera coordinates.
    view = read_sequence(seq_dir).views[0]
    rows = read_bop_results(out)
    assert [r[1] for r in rows] == view.frame_ids == [0, 1, 2]
    np.testing.assert_allclose(rows[0][4], view.T_cam_obj[1][0], atol=1e-5)
    for k in (1, 2):
        np.testing.assert_allclose(rows[k][4], view.T_cam_world @ fake.truth(k) @ _turn(TURN_DEG[k]), atol=1e-5)
    assert [r[3] for r in rows] == [1.0, 0.9, 0.2]
    records = [json.loads(line) for line in out.with_name("run.frames.jsonl").read_text().splitlines()]
    assert [r["status"] for r in records] == ["OK", "OK", "LOST"]
    assert records[1]["counts"] == {"0": {"region": 7, "flow": 7, "sift": 7}} and records[1]["reset"] is False
    assert "step_s" in records[1]["timings"] and "total_s" in records[1]["timings"]
    assert records[0]["crop"] is None and records[1]["crop"] == [40, 50]
    frames = _video_frames(video)
    assert len(frames) == 3 and frames[0].shape == (H, W, 3)

    assert main(["eval", str(out), str(seq_dir)]) == 0
    text = capsys.readouterr().out
    per_frame = {int(m[0]): (float(m[1]), m[2]) for m in re.findall(r"^\| (\d+) \| ([\d.]+) \| [\d.]+ \| [\d.]+ \| "
                                                                        r"[\d.]+ \| (\w+) \|", text, re.MULTILINE)}
    assert per_frame[0][0] == pytest.approx(0.0, abs=1e-3)
    # The fake's turns, read back through CSV + eval (the CSV keeps R to 8 decimals).
    assert per_frame[1] == (pytest.approx(TURN_DEG[1], abs=2e-3), "yes")
    assert per_frame[2] == (pytest.approx(TURN_DEG[2], abs=2e-3), "NO")
    assert "| 5 cm / 5° success | 0.500 (1/2) |" in text
    assert "the first frame, the given initial pose, left out" in text
    # Frame 2 is the one failure and the one LOST frame: precision = recall = 1.
    assert "| lost | 1 | 1.000 | 1.000 |" in text


def test_video_as_png_folder_with_chosen_cues_and_init_pose(seq_dir, fake, tmp_path, capsys):
    view = read_sequence(seq_dir).views[0]
    T0 = view.T_cam_obj[1][0].copy()
    T0[:3, 3] += [5.0, -3.0, 10.0]
    np.save(tmp_path / "init.npy", T0)
    pngs = tmp_path / "frames"
    argv = ["track", str(seq_dir), "-o", str(tmp_path / "r.csv"), "--video", str(pngs), "--cues", "region,sift",
            "--init-pose", str(tmp_path / "init.npy"), "--max-frames", "2", "--quiet", "--no-cache"]
    assert main(argv) == 0
    assert fake.built[0].cues == ("region", "sift")
    np.testing.assert_allclose(view.T_cam_world @ fake.built[0].start_pose, T0, atol=1e-9)
    assert sorted(p.name for p in pngs.iterdir()) == ["000000.png", "000001.png"]
    assert len(read_bop_results(tmp_path / "r.csv")) == 2


def test_reset_on_failure_restarts_from_the_truth_and_is_recorded(seq_dir, fake, tmp_path, capsys):
    out = tmp_path / "rbot.csv"
    assert main(["track", str(seq_dir), "-o", str(out), "--reset-on-failure", "--quiet", "--no-cache"]) == 0
    assert "resets 1" in capsys.readouterr().out
    np.testing.assert_allclose(fake.built[0].starts[1], fake.truth(2), atol=1e-9)  # frame 2 failed: restarted there
    records = [json.loads(line) for line in out.with_name("rbot.frames.jsonl").read_text().splitlines()]
    assert [r["reset"] for r in records] == [False, False, True]
    assert main(["eval", str(out), str(seq_dir)]) == 0
    text = capsys.readouterr().out
    assert "resets (RBOT protocol): 1" in text and "| 2 | 15.000 |" in text and "LOST (reset) |" in text


def test_two_views_tile_the_overlay_and_write_rows_per_view(fake, tmp_path, capsys):
    from jaxtrack.synth import SynthConfig, write_sequence

    cfg = SynthConfig(object="box", appearance="flat", size_mm=160, motion="random", step_px=3, step_deg=1.5, frames=3,
                      cameras=2, width=W, height=H, focal=175, background="flat", seed=1)
    seq2 = write_sequence(cfg, tmp_path / "seq2")
    fake.truth = staticmethod(_world_truth(seq2))
    out = tmp_path / "two.csv"
    assert main(["track", str(seq2), "-o", str(out), "--cameras", "1,0", "--video", str(tmp_path / "two"), "--quiet",
                 "--no-cache"]) == 0
    assert fake.built[0].num_cameras == 2
    assert cv2.imread(str(tmp_path / "two" / "000002.png")).shape == (H, 2 * W, 3)  # the views side by side
    rows = read_bop_results(out)
    assert sorted((r[0], r[1]) for r in rows) == [(v, k) for v in (0, 1) for k in range(3)]
    capsys.readouterr()
    # Both views see the one world pose: the same rotation errors (the fake's turns) from either.
    for view in ("0", "1"):
        assert main(["eval", str(out), str(seq2), "--camera", view]) == 0
        text = capsys.readouterr().out
        assert f"view {view}, obj_id 1" in text
        rot = float(re.search(r"^\| 2 \| ([\d.]+) \|", text, re.MULTILINE)[1])
        assert rot == pytest.approx(TURN_DEG[2], abs=2e-3)


def test_overlay_shows_the_pose_it_was_given(seq_dir, fake, tmp_path):
    """The model contour in the overlay follows the estimated pose: frame 2 (turned 15°) is off the contour
    at the true pose, frame 1 (0.5°) on it. PNGs: lossless (mp4 blurs the colour of 1-px lines)."""
    pngs = tmp_path / "o"
    assert main(["track", str(seq_dir), "-o", str(tmp_path / "r.csv"), "--video", str(pngs), "--quiet", "--no-cache"]) == 0
    frames = [cv2.cvtColor(cv2.imread(str(pngs / f"{k:06d}.png")), cv2.COLOR_BGR2RGB) for k in range(3)]
    seq = read_sequence(seq_dir)
    from jaxtrack.io import load_trimesh

    tm = load_trimesh(seq.model_paths[1])
    view = seq.views[0]
    green = [np.all(f == MODEL_COLOUR, axis=-1) for f in frames]

    def share_near(k, T):  # share of the drawn model contour within 1 px of the silhouette outline at T
        sil = model_mask(tm.vertices @ T[:3, :3].T + T[:3, 3], tm.faces, view.K, (H, W))
        edge = sil & ~cv2.erode(sil.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        near = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        return green[k][near].sum() / green[k].sum()

    for k in (0, 1, 2):
        T_est = view.T_cam_obj[1][0] if k == 0 else view.T_cam_world @ fake.truth(k) @ _turn(TURN_DEG[k])
        assert green[k].sum() > 50 and share_near(k, T_est) > 0.95
    assert share_near(2, view.T_cam_obj[1][2]) < share_near(2, view.T_cam_world @ fake.truth(2) @ _turn(TURN_DEG[2])) - 0.2


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--cameras", "1"], "--cameras: view 1 out of range: .* has 1 camera view"),
        (["--obj-id", "7"], "--obj-id: object 7 has no mesh"),
        (["-o", "{d}/a_file/r.csv"], "-o/--out: cannot create folder .*a_file is a file"),
        (["-o", "{d}/r.txt"], "-o/--out: .*r.txt must end in one of .csv"),
        (["-o", "{d}"], "-o/--out: .* is a folder"),
        (["--video", "{d}/a_file/v.mp4"], "--video: cannot create folder .*a_file is a file"),
        (["--video", "{d}/a_file"], "--video: .*a_file exists and is not a folder"),
        (["--init-pose", "1,2,3"], "--init-pose: the numbers given holds 3 numbers; need 12"),
        (["--init-pose", "{d}/none.npy"], "--init-pose: '.*none.npy' is neither a file nor 12 / 16 numbers"),
        (["--init-pose", "2,0,0,0, 0,1,0,0, 0,0,1,500"], "--init-pose: the rotation block"),
        (["--init-pose", "1,0,0,0, 0,1,0,0, 0,0,1,-500"], "--init-pose: .*behind the camera"),
        (["--init-pose", "1,0,0,0, 0,1,0,0, 0,0,1,500, 0,0,0,2"], "--init-pose: the last row must be 0 0 0 1"),
        (["--init-pose", "{d}/pose.json"], "--init-pose: .*pose.json: cannot read a pose .*cam_R_m2c"),
    ],
)
def test_track_refuses_bad_input_before_tracking(seq_dir, fake, tmp_path, capsys, extra, message):
    (tmp_path / "a_file").write_text("not a folder")
    (tmp_path / "pose.json").write_text(json.dumps({"R": [1, 0, 0]}))
    argv = ["track", str(seq_dir), *(x.format(d=tmp_path) for x in extra), "--quiet", "--no-cache"]
    if "-o" not in extra:
        argv += ["-o", str(tmp_path / "out.csv")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxtrack track: error: ") and "Traceback" not in err
    assert re.search(message, err), err
    assert not fake.built  # refused before the tracker (and any compilation) existed
    assert not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--cues", "region,colour"], "argument --cues: unknown cue 'colour' \\(choose from region, levelset, lines, flow, sift"),
        (["--cues", "flow,flow"], "argument --cues: a cue is named twice"),
        (["--cameras", "0,-1"], "argument --cameras: expected distinct view indices ≥ 0"),
        (["--cameras", "a"], "argument --cameras: expected comma-separated view indices"),
        (["--max-frames", "0"], "argument --max-frames: must be ≥ 1, got 0"),
        (["--late-rounds", "3"], "argument --late-rounds: expected K,F\\[,T\\]: K ≥ 0"),
        (["--late-rounds", "3,1.5"], "argument --late-rounds: expected K,F\\[,T\\]: K ≥ 0 \\(inf: every round\\), F and T in"),
        (["--late-rounds=-1,0.3,0.9"], "argument --late-rounds: expected K,F\\[,T\\]: K ≥ 0"),
        (["--late-rounds", "3,0.3,x"], "argument --late-rounds: expected K,F\\[,T\\] \\(numbers\\)"),
    ],
)
def test_track_option_values(seq_dir, fake, tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["track", str(seq_dir), "-o", str(tmp_path / "o.csv"), *argv])
    assert exit_info.value.code == 2
    assert re.search("jaxtrack track: error: " + message, capsys.readouterr().err)
    assert not fake.built


def test_late_rounds_reach_the_tracker_only_when_given(seq_dir, fake, tmp_path):
    """`--late-rounds K,F[,T]` is handed to the tracker as `late_rounds` (K = inf allowed); without it the tracker
    gets no such option (its defaults: every round)."""
    assert main(["track", str(seq_dir), "-o", str(tmp_path / "a.csv"), "--late-rounds", "3,0.3,0.9", "--quiet",
                 "--no-cache"]) == 0
    assert fake.built[-1].options == {"late_rounds": (3.0, 0.3, 0.9)}
    assert main(["track", str(seq_dir), "-o", str(tmp_path / "b.csv"), "--late-rounds", "inf,0", "--quiet", "--no-cache"]) == 0
    assert fake.built[-1].options == {"late_rounds": (float("inf"), 0.0)}
    assert main(["track", str(seq_dir), "-o", str(tmp_path / "c.csv"), "--quiet", "--no-cache"]) == 0
    assert fake.built[-1].options == {}


def test_track_names_a_missing_or_broken_sequence(fake, tmp_path, seq_dir, capsys):
    assert main(["track", str(tmp_path / "nowhere"), "-o", str(tmp_path / "o.csv")]) == 2
    assert re.search("jaxtrack track: error: .*nowhere: no such BOP sequence folder, video file or folder of images",
                     capsys.readouterr().err)
    # A sequence without ground truth after frame 0 cannot run the RBOT protocol; nor without frame 0's pose.
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(seq_dir, copy)
    gt_path = copy / "000000" / "scene_gt.json"
    gt = json.loads(gt_path.read_text())
    gt_path.write_text(json.dumps({k: (v if k == "0" else []) for k, v in gt.items()}))
    assert main(["track", str(copy), "-o", str(tmp_path / "o.csv"), "--reset-on-failure"]) == 2
    assert "--reset-on-failure: " in capsys.readouterr().err
    gt_path.write_text(json.dumps({k: [] for k in gt}))
    assert main(["track", str(copy), "-o", str(tmp_path / "o.csv")]) == 2
    assert "no pose of obj_id 1 for the first frame; give one with --init-pose" in capsys.readouterr().err
    assert not fake.built and not (tmp_path / "o.csv").exists()


def test_init_pose_formats(tmp_path):
    T = make_transform(np.asarray(so3_exp(np.array([0.1, -0.2, 0.3]))), np.array([10.0, 20.0, 600.0]))
    np.save(tmp_path / "p.npy", T)
    (tmp_path / "p.json").write_text(json.dumps(T[:3].tolist()))
    (tmp_path / "bop.json").write_text(json.dumps({"cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist()}))
    np.savetxt(tmp_path / "p.txt", T)
    inline = ",".join(f"{v:.17g}" for v in T[:3].ravel())
    for source in (tmp_path / "p.npy", tmp_path / "p.json", tmp_path / "bop.json", tmp_path / "p.txt", inline):
        np.testing.assert_allclose(read_init_pose(str(source)), T, atol=1e-12)


def test_eval_refuses_results_of_another_sequence(seq_dir, tmp_path, capsys):
    from jaxtrack.io import write_bop_results

    T = np.eye(4)
    T[2, 3] = 500.0
    write_bop_results(tmp_path / "other.csv", [(0, 0, 1, 1.0, T, 0.1), (0, 57, 1, 1.0, T, 0.1)])
    assert main(["eval", str(tmp_path / "other.csv"), str(seq_dir)]) == 2
    assert re.search("jaxtrack eval: error: .*other.csv: im_id 57 is not a frame of .*000000", capsys.readouterr().err)
    write_bop_results(tmp_path / "twice.csv", [(0, 1, 1, 1.0, T, 0.1), (0, 1, 1, 1.0, T, 0.1)])
    assert main(["eval", str(tmp_path / "twice.csv"), str(seq_dir)]) == 2
    assert "two rows for view 0, im_id 1" in capsys.readouterr().err
    write_bop_results(tmp_path / "obj2.csv", [(0, 1, 2, 1.0, T, 0.1)])
    assert main(["eval", str(tmp_path / "obj2.csv"), str(seq_dir)]) == 2
    assert "obj_id 2 has no mesh" in capsys.readouterr().err
    write_bop_results(tmp_path / "cam1.csv", [(1, 1, 1, 1.0, T, 0.1)])
    assert main(["eval", str(tmp_path / "cam1.csv"), str(seq_dir)]) == 2
    assert "scene_id 1 is not a camera view" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "missing.csv"), str(seq_dir)]) == 2
    assert "missing.csv: missing" in capsys.readouterr().err
    assert main(["eval", str(tmp_path), str(seq_dir)]) == 2
    assert "is a folder; expected the results CSV" in capsys.readouterr().err
    # a byte-order mark before the header (a spreadsheet's export) is not a malformed header
    bom = tmp_path / "bom.csv"
    write_bop_results(bom, [(0, 0, 1, 1.0, T, 0.1), (0, 1, 1, 1.0, T, 0.1)])
    bom.write_bytes(b"\xef\xbb\xbf" + bom.read_bytes())
    assert main(["eval", str(bom), str(seq_dir), "--summary"]) == 0
    capsys.readouterr()
    # only the first frame (the given pose): nothing to evaluate is an error, not an empty table and exit 0
    write_bop_results(tmp_path / "first.csv", [(0, 0, 1, 1.0, T, 0.1)])
    assert main(["eval", str(tmp_path / "first.csv"), str(seq_dir)]) == 2
    assert "first.csv: none of its 1 frame(s) after the first has a ground-truth pose" in capsys.readouterr().err
    # a frames.jsonl whose status is not a status name, or whose confidence is not a number, is refused by line
    write_bop_results(tmp_path / "typo.csv", [(0, 0, 1, 1.0, T, 0.1), (0, 1, 1, 1.0, T, 0.1)])
    for line, message in (('{"im_id": 1, "status": "Ok", "confidence": 0.9}', "field 'status' is 'Ok', not a status name"),
                          ('{"im_id": 1, "status": "OK", "confidence": "high"}', "field 'confidence' is 'high', not a finite")):
        (tmp_path / "typo.frames.jsonl").write_text('{"im_id": 0, "status": "OK", "confidence": 1.0}\n' + line + "\n")
        assert main(["eval", str(tmp_path / "typo.csv"), str(seq_dir)]) == 2
        err = capsys.readouterr().err
        assert "typo.frames.jsonl:2: " + message in err, err


def test_demo_tracks_reports_and_fails_loudly(fake, tmp_path, monkeypatch, capsys):
    """The demo's own logic with the fake tracker: synthesis, tracking, overlay, errors, exit status."""
    import jaxtrack.cli

    monkeypatch.setattr(jaxtrack.cli, "DEMO_SIZE", (W, H))
    out = tmp_path / "demo"
    fake.truth = staticmethod(lambda k: _world_truth(out / "sequence")(k))
    assert main(["demo", "--frames", "3", "--out", str(out), "--quiet", "--no-cache"]) == 1  # frame 2 is 15° off
    text = capsys.readouterr()
    assert f"overlay video -> {out / 'overlay.mp4'} (3 frames)" in text.out
    assert "| 5 cm / 5° success | 0.500 (1/2) |" in text.out
    assert "tracking failed badly: 1 frame(s) beyond 5 cm / 5°" in text.err
    assert len(_video_frames(out / "overlay.mp4")) == 3
    monkeypatch.setitem(TURN_DEG, 2, 1.0)  # now every frame is within 5°: exit 0; a second run replaces the sequence
    assert main(["demo", "--frames", "3", "--out", str(out), "--quiet", "--no-cache"]) == 0
    assert "| 5 cm / 5° success | 1.000 (2/2) |" in capsys.readouterr().out
    (tmp_path / "mine" / "sequence").mkdir(parents=True)
    assert main(["demo", "--frames", "3", "--out", str(tmp_path / "mine"), "--quiet"]) == 2
    assert "is not a jaxtrack demo sequence" in capsys.readouterr().err


def test_overlay_draws_only_on_the_contours():
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (2, 60, 80, 3)).astype(np.float32)
    K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])
    # A square of side 40 mm at 200 mm: 20 px, as two triangles (camera 0); shifted right in camera 1.
    square = np.array([[-20.0, -20, 200], [20, -20, 200], [20, 20, 200], [-20, 20, 200]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    p_cam = [square, square + [20.0, 0, 0]]
    phi = -np.ones((2, 10, 12))
    phi[:, 3:7, 4:9] = 1.0
    offsets = np.array([[5, 6], [54, 72]])  # camera 1's crop runs past the image border (clipped)
    out = overlay_frame(images, p_cam, faces, K, region_phi=phi, offsets=offsets)
    assert out.shape == (60, 160, 3) and out.dtype == np.uint8
    base = np.concatenate(list(images.astype(np.uint8)), axis=1)
    changed = np.any(out != base, axis=-1)
    sil0 = model_mask(square, faces, K, (60, 80))
    inside = np.zeros((60, 80), bool)
    inside[20:40, 30:50] = True  # pixel centres inside the square's image [29.5, 49.5] x [19.5, 39.5]
    around = np.zeros((60, 80), bool)
    around[19:41, 29:51] = True  # OpenCV's fill may take pixels up to half a pixel outside
    assert np.all(sil0[inside]) and not np.any(sil0[~around])
    seg1 = segmentation_mask(phi[1], offsets[1], (60, 80))
    assert seg1.sum() == 12 and seg1[57:60, 76:80].all()  # 3 of 4 rows, 4 of 5 columns inside the image
    sil1 = model_mask(p_cam[1], faces, K, (60, 80))
    assert np.array_equal(sil1, np.roll(sil0, 10, axis=1))  # 20 mm at 200 mm: 10 px

    def edge(mask):  # the outline: mask pixels with a 4-neighbour outside (or beyond the border)
        inner = cv2.erode(mask.astype(np.uint8), np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8),
                          borderType=cv2.BORDER_CONSTANT, borderValue=0)
        return mask & ~inner.astype(bool)

    model_edge = np.concatenate([edge(sil0), edge(sil1)], axis=1)
    seg_edge = np.concatenate([edge(segmentation_mask(phi[0], offsets[0], (60, 80))), edge(seg1)], axis=1)
    assert seg_edge[:, :80].sum() == 14 and seg_edge[:, 80:].sum() == 10
    assert np.all(out[model_edge] == MODEL_COLOUR)
    assert np.all(out[seg_edge & ~model_edge] == SEGMENT_COLOUR)
    assert not np.any(changed & ~model_edge & ~seg_edge)  # nothing but the contours
    # Coinciding contours with 2-px lines: the segmentation (1 px) on top of the model's line, both visible.
    thick = overlay_frame(images[:1], p_cam[:1], faces, K, region_phi=np.where(sil0, 1.0, -1.0)[None],
                          offsets=np.zeros((1, 2), int), thickness=2)
    assert np.all(thick[edge(sil0)] == SEGMENT_COLOUR)
    assert np.sum(np.all(thick == MODEL_COLOUR, axis=-1)) > 0.5 * edge(sil0).sum()
    # Overlapping triangles make a union, not the even-odd pattern of cv2.fillPoly.
    two = model_mask(np.vstack([square, square + [10.0, 10, 0]]), np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]),
                     K, (60, 80))
    assert np.array_equal(two, sil0 | np.roll(sil0, (5, 5), axis=(0, 1)))  # the copy is 5 px down and right
    # Behind the camera: nothing drawn, nothing raised.
    assert not model_mask(square * [1, 1, -1], faces, K, (60, 80)).any()
    with_text = overlay_frame(images[:1], p_cam[:1], faces, K, text="frame 0  OK  conf 1.00")
    assert np.any(with_text[:12, :60] != images[0, :12, :60].astype(np.uint8))


def test_overlay_writer_checks_its_path_and_frames(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="--video: .*f exists and is not a folder"):
        OverlayWriter(tmp_path / "f", (10, 20), what="--video")
    with OverlayWriter(tmp_path / "v.avi", (10, 20)) as w:
        with pytest.raises(ValueError, match=r"frames must be \(10, 20, 3\) uint8"):
            w.write(np.zeros((10, 21, 3), np.uint8))
        w.write(np.zeros((10, 20, 3), np.uint8))
    assert w.count == 1 and len(_video_frames(tmp_path / "v.avi")) == 1


def test_real_track_and_eval_end_to_end(seq_dir, tmp_path, capsys):
    """The real tracker (region cue only, frames 0-1 of 160x120: one compiled step) through the CLI, then eval.

    This checks the plumbing with the real `Tracker` (finite poses, scores in [0, 1], one overlay frame
    per frame, eval's errors equal to the CSV's); test_tracker checks the accuracy.
    """
    from jaxtrack.geometry import rotation_error_deg

    out = tmp_path / "real.csv"
    start = time.perf_counter()
    rc = main(["track", str(seq_dir), "-o", str(out), "--cues", "region", "--max-frames", "2",
               "--video", str(tmp_path / "real.mp4"), "--quiet", "--no-cache"])
    seconds = time.perf_counter() - start
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "status: " in text and f"results -> {out}" in text
    rows = read_bop_results(out)
    assert [r[1] for r in rows] == [0, 1] and all(np.all(np.isfinite(r[4])) for r in rows)
    assert all(0.0 <= r[3] <= 1.0 for r in rows)
    records = [json.loads(line) for line in out.with_name("real.frames.jsonl").read_text().splitlines()]
    assert records[1]["counts"]["0"]["region"] > 0 and set(records[1]["counts"]["0"]) == {"region"}  # configured cues only
    assert len(_video_frames(tmp_path / "real.mp4")) == 2
    assert main(["eval", str(out), str(seq_dir)]) == 0
    text = capsys.readouterr().out
    printed = float(re.search(r"^\| 1 \| ([\d.]+) \|", text, re.MULTILINE)[1])
    truth = read_sequence(seq_dir).views[0].T_cam_obj[1][1]
    assert printed == pytest.approx(float(rotation_error_deg(rows[1][4][:3, :3], truth[:3, :3])), abs=1e-3)
    print(f"real track (region, 2 frames) {seconds:.1f} s; frame 1 rotation error {printed}°")


@pytest.mark.parametrize("flags, searches", [((), True), (("--no-recover",), False), (("--reset-on-failure",), False),
                                             (("--reset-on-failure", "--recover"), True), (("--recover",), True)])
def test_track_searches_after_a_lost_frame_unless_reset_or_told_not_to(seq_dir, fake, tmp_path, flags, searches):
    """`jaxtrack track` builds its tracker with the search after a LOST frame (`TrackerConfig.recovery`) by default,
    without it for --no-recover and for the RBOT protocol's resets (the oracle), with it when asked."""
    assert main(["track", str(seq_dir), "-o", str(tmp_path / "r.csv"), "--quiet", "--no-cache", *flags]) == 0
    (tracker,) = fake.built
    assert (tracker.config.recovery is not None) == searches, (flags, tracker.config.recovery)


def test_the_progress_bar_keeps_its_clock_running_through_a_long_frame():
    """`track_sequence`'s bar during a long frame (the set-up, a compile): after a second it is redrawn with what runs
    (the view model's views once the build reports them) and the seconds so far; after `idle` it is left alone."""
    import io

    from tqdm import tqdm

    out = io.StringIO()
    bar = tqdm(total=3, file=out, mininterval=0)
    heartbeat = sequence_module._BarHeartbeat(bar, period=0.1)
    try:
        heartbeat.busy("set-up")
        heartbeat.views(8, 12)
        time.sleep(1.5)
        heartbeat.idle()
        time.sleep(0.05)  # a redraw already under way ends
        shown = out.getvalue()
        time.sleep(0.4)
        assert out.getvalue() == shown  # idle: no more redraws
        assert not bar.postfix  # and its text cleared for the frame's own postfix
    finally:
        heartbeat.close()
    assert "set-up: view model 8/12 views (1 s)" in shown
    none = sequence_module._BarHeartbeat(None)  # no bar: no thread, nothing to do
    none.busy("x")
    none.close()
