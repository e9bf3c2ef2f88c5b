"""The command line on bad input: every user mistake is caught before the work, named, exit status 2.

The flow solve itself is exercised end to end in test_flow_solver.py; here `compute_flow` is replaced
by a stand-in that records its calls, so the checks can assert the solve never started (or, on good
input, that exactly its result was written where the user asked).
"""

import re

import cv2
import numpy as np
import pytest

import jaxtrack.cues.flow
from jaxtrack._status import Status, StatusError
from jaxtrack.cli import main
from jaxtrack.io import read_flo, write_flo


class _FakeSolve:
    """Stands in for compute_flow: returns a fixed flow, or raises `error`; counts calls."""

    def __init__(self, error=None):
        self.calls = 0
        self.error = error

    def __call__(self, img1, img2, params, config, region=None):
        self.calls += 1
        if self.error is not None:
            raise self.error
        h, w = img1.shape[:2]
        flow = np.zeros((h, w, 2), np.float32)
        flow[..., 0], flow[..., 1] = 1.5, -0.5
        return type("Result", (), {"flow": flow})()


@pytest.fixture
def frames(tmp_path):
    rng = np.random.default_rng(0)
    a = (rng.random((24, 32)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), np.roll(a, 1, axis=1))
    cv2.imwrite(str(tmp_path / "small.png"), a[:10])
    cv2.imwrite(str(tmp_path / "rgba.png"), np.stack([np.roll(a, 1, axis=1)] * 3 + [np.full_like(a, 255)], -1))
    cv2.imwrite(str(tmp_path / "empty_mask.png"), np.zeros_like(a))
    write_flo(tmp_path / "gt_small.flo", np.zeros((10, 32, 2)))
    (tmp_path / "a_file").write_text("not a folder")
    return tmp_path


@pytest.fixture
def fake_solve(monkeypatch):
    fake = _FakeSolve()
    monkeypatch.setattr(jaxtrack.cues.flow, "compute_flow", fake)
    return fake


def test_flow_creates_output_folders_and_writes_what_it_promised(frames, fake_solve, capsys):
    out, viz = frames / "new" / "dir" / "f.flo", frames / "other" / "v.png"
    rc = main(["flow", str(frames / "a.png"), str(frames / "b.png"), "-o", str(out), "--viz", str(viz), "--no-cache"])
    assert rc == 0 and fake_solve.calls == 1
    flow = read_flo(out)
    assert flow.shape == (24, 32, 2) and np.all(flow[..., 0] == 1.5) and np.all(flow[..., 1] == -0.5)
    assert cv2.imread(str(viz)).shape == (24, 32, 3)
    assert str(viz) in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["-o", "{d}/nodir/v"], "-o/--out: .*/nodir/v must end in one of .flo"),
        (["-o", "{d}/out.png"], "-o/--out: .*out.png must end in one of .flo"),
        (["-o", "{d}/a_file/x.flo"], "-o/--out: cannot create folder .*a_file is a file"),
        (["-o", "{d}/out.flo", "--viz", "{d}/nodir/viz"], "--viz: .*nodir/viz: no image writer for extension ''"),
        (["-o", "{d}/out.flo", "--viz", "{d}"], "--viz: .* no image writer|is a folder"),
        (["-o", "{d}/out.flo", "--region", "{d}/small.png"], "--region: .*small.png is 32x10, the frames are 32x24"),
        (["-o", "{d}/out.flo", "--region", "{d}/empty_mask.png"], "--region: .*has no non-zero pixel"),
        (["-o", "{d}/out.flo", "--gt", "{d}/gt_small.flo"], "--gt: .*gt_small.flo is 32x10"),
        (["-o", "{d}/out.flo", "--gt", "{d}/a.png"], "a.png: not a .flo file"),
        (["-o", "{d}/out.flo", "--gt", "{d}/none.flo"], "none.flo: flow file not found"),
    ],
)
def test_flow_checks_outputs_and_inputs_before_solving(frames, fake_solve, capsys, extra, message):
    argv = ["flow", str(frames / "a.png"), str(frames / "b.png"), *(x.format(d=frames) for x in extra), "--no-cache"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxtrack flow: error: ") and "Traceback" not in err
    assert any(re.search(m, err) for m in message.split("|")), err
    assert fake_solve.calls == 0
    assert not (frames / "out.flo").exists()


@pytest.mark.parametrize(
    "frame1, frame2, message",
    [
        ("missing.png", "b.png", "missing.png: image file not found"),
        ("a.png", "small.png", "frames differ in size: .*a.png is 32x24, .*small.png is 32x10"),
        ("a_file", "b.png", "a_file: cannot read image"),
    ],
)
def test_flow_names_unreadable_or_mismatched_frames(frames, fake_solve, capsys, frame1, frame2, message):
    assert main(["flow", str(frames / frame1), str(frames / frame2), "-o", str(frames / "o.flo"), "--no-cache"]) == 2
    err = capsys.readouterr().err
    assert re.search("jaxtrack flow: error: .*" + message, err), err
    assert fake_solve.calls == 0


@pytest.mark.parametrize(
    "option, value, message",
    [
        ("--epsilon", "0", "argument --epsilon: must be > 0, got 0"),
        ("--epsilon", "nan", "argument --epsilon: must be finite"),
        ("--alpha", "-1", "argument --alpha: must be ≥ 0, got -1"),
        ("--gamma", "-0.5", "argument --gamma: must be ≥ 0"),
        ("--eta", "1.5", "argument --eta: must be > 0 and < 1"),
        ("--eta", "1", "argument --eta: must be > 0 and < 1, got 1"),
        ("--warps", "0", "argument --warps: must be ≥ 1"),
        ("--sor", "two", "argument --sor: expected an integer, got 'two'"),
        ("--sigma", "-1", "argument --sigma: must be ≥ 0"),
    ],
)
def test_flow_parameters_are_validated_before_anything_runs(frames, fake_solve, capsys, option, value, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["flow", str(frames / "a.png"), str(frames / "b.png"), "-o", str(frames / "o.flo"), option, value])
    assert exit_info.value.code == 2
    assert "jaxtrack flow: error: " + message in capsys.readouterr().err
    assert fake_solve.calls == 0 and not (frames / "o.flo").exists()


def test_a_grey_and_a_colour_frame_are_compared_in_grey(frames, fake_solve, capsys):
    assert main(["flow", str(frames / "a.png"), str(frames / "rgba.png"), "-o", str(frames / "o.flo"), "--no-cache"]) == 0
    assert re.search(r"note: .*a\.png is grey, the other frame colour: both are read as grey", capsys.readouterr().out)
    assert fake_solve.calls == 1 and (frames / "o.flo").exists()


def test_synth_poses_behind_the_camera_are_named_and_leave_no_folder(frames, capsys):
    poses = np.repeat(np.eye(4)[None], 3, 0)
    poses[:, 2, 3] = -900.0
    np.save(frames / "behind.npy", poses)
    argv = ["synth", str(frames / "s"), "--motion", "file", "--pose-file", str(frames / "behind.npy"), "--frames", "3", "--quiet"]
    assert main(argv) == 2
    assert re.search(r"behind.npy: pose 0 puts the object behind camera 0 \(depth -\d+", capsys.readouterr().err)
    assert not (frames / "s").exists()


def test_a_twist_of_the_wrong_length_is_named():
    from jaxtrack.geometry import se3_exp, so3_log

    with pytest.raises(ValueError, match=r"se3_exp: the input must have shape \(\.\.\., 6\), got \(5,\)"):
        se3_exp(np.zeros(5))
    with pytest.raises(ValueError, match=r"so3_log: the input must have shape \(\.\.\., 3, 3\), got \(4, 4\)"):
        so3_log(np.eye(4))


def test_a_failed_solve_exits_1_with_its_status(frames, monkeypatch, capsys):
    monkeypatch.setattr(jaxtrack.cues.flow, "compute_flow", _FakeSolve(StatusError(Status.NONFINITE, "compute_flow")))
    assert main(["flow", str(frames / "a.png"), str(frames / "b.png"), "-o", str(frames / "o.flo"), "--no-cache"]) == 1
    assert capsys.readouterr().err.startswith("jaxtrack flow: compute_flow: NONFINITE")
    assert not (frames / "o.flo").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--frames", "-3", "{d}/s"], "argument --frames: must be ≥ 1, got -3"),
        (["--cameras", "0", "{d}/s"], "argument --cameras: must be ≥ 1 and ≤ 4, got 0"),
        (["--cameras", "5", "{d}/s"], "argument --cameras: must be ≥ 1 and ≤ 4, got 5"),
        (["--salt-fraction", "1.5", "{d}/s"], "argument --salt-fraction: must be ≥ 0 and ≤ 1"),
        (["--occluders", "-1", "{d}/s"], "argument --occluders: must be ≥ 0"),
        (["--seed", "-2", "{d}/s"], "argument --seed: must be ≥ 0"),
    ],
)
def test_synth_option_ranges(frames, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["synth", *(x.format(d=frames) for x in argv)])
    assert exit_info.value.code == 2
    assert "jaxtrack synth: error: " + message in capsys.readouterr().err
    assert not (frames / "s").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["{d}/a_file", "--frames", "1"], "output folder: .*a_file exists and is not a folder"),
        (["{d}/s", "--object", "{d}/none.obj", "--frames", "1"], "SynthConfig.object .*none.obj: mesh file not found"),
        (["{d}/s", "--background", "moon"], "SynthConfig.background must be one of"),
        (["{d}/s", "--motion", "file"], "SynthConfig.pose_file: motion 'file' needs"),
        (["{d}/s", "--preset", "nope"], "unknown preset 'nope'"),
        ([], "an output folder is required"),
    ],
)
def test_synth_bad_values_are_named_before_rendering(frames, capsys, argv, message):
    assert main(["synth", "--quiet", *(x.format(d=frames) for x in argv)]) == 2
    err = capsys.readouterr().err
    assert re.search("jaxtrack synth: error: " + message, err), err
    assert not (frames / "s").exists()


@pytest.mark.parametrize("option, value", [("--frames", "0"), ("--cameras", "0"), ("--points", "0"), ("--noise", "-1")])
def test_demo_option_ranges(capsys, option, value):
    with pytest.raises(SystemExit) as exit_info:
        main(["demo", option, value])
    assert exit_info.value.code == 2
    assert f"jaxtrack demo: error: argument {option}: must be" in capsys.readouterr().err


def test_demo_solver_only_keeps_the_pose_solver_demo(capsys):
    """`jaxtrack demo --solver-only`: the earlier demo (noisy 2D-3D correspondences, no images)."""
    assert main(["demo", "--solver-only", "--frames", "2", "--joints", "0", "--cameras", "1", "--points", "30", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "1 part(s), 0 joint(s), 1 camera(s), 30 correspondences/frame" in out and "2 frames" in out
    assert "solver status OK on 2/2 frames" in out


def test_recover_is_on_by_default_and_can_be_turned_off():
    """`jaxtrack track` and `jaxtrack bench`: --recover / --no-recover, None (the default: on without resets)."""
    from jaxtrack.cli import build_parser

    parser = build_parser()
    for command in ("track", "bench"):
        assert parser.parse_args([command, "seq"]).recover is None
        assert parser.parse_args([command, "seq", "--recover"]).recover is True
        assert parser.parse_args([command, "seq", "--no-recover"]).recover is False


def test_late_rounds_are_an_option_of_track_and_bench_and_a_bench_setting():
    """`--late-rounds K,F[,T]` parses for `jaxtrack track` and `jaxtrack bench` (None by default: every round); the
    bench keeps it among the settings a resumed bench must share, and refuses a bad value before any job."""
    from jaxtrack.bench import BenchSettings
    from jaxtrack.cli import build_parser

    parser = build_parser()
    for command in ("track", "bench"):
        assert parser.parse_args([command, "seq"]).late_rounds is None
        assert parser.parse_args([command, "seq", "--late-rounds", "3,0.3,0.9"]).late_rounds == (3.0, 0.3, 0.9)
    assert BenchSettings().tracker_dict()["late_rounds"] is None
    assert BenchSettings(late_rounds=(3, 0.3, 0.9)).tracker_dict()["late_rounds"] == [3, 0.3, 0.9]
    for bad in ((3, 2.0), (-1, 0.3), (3,), "fast"):
        with pytest.raises(ValueError, match="--late-rounds: late_rounds must be"):
            BenchSettings(late_rounds=bad)
