"""`jaxtrack bench` and what it stands on: the dataset readers (BCOT's layout, BOP scenes with several objects, frame
steps), results written frame by frame with a partial marker, the bench's resume and failure reporting, and a Ray
run that equals the sequential one (started and stopped inside the test)."""

import json
import pathlib
import shutil

import numpy as np
import pytest

pytestmark = pytest.mark.xdist_group("bench")


def _pose_columns(csv: pathlib.Path) -> list[str]:
    """scene_id,im_id,obj_id,score,R,t of every row (time left out: it is measured)."""
    return [",".join(line.split(",")[:6]) for line in csv.read_text().splitlines()]


@pytest.fixture(scope="module")
def rbot_synth(tmp_path_factory):
    """A synthetic RBOT-layout dataset: the box in the three synthetic variants, 6 frames at 160x120."""
    from jaxtrack.synth import RbotSynthConfig, write_rbot_dataset

    root = tmp_path_factory.mktemp("rbot-synth") / "RBOT"
    cfg = RbotSynthConfig(objects=("box",), variants=("a_regular", "b_dynamiclight", "c_noisy"), frames=6, width=160,
                          height=120, focal=175.0, step_px=3.0, step_deg=2.0)
    return write_rbot_dataset(cfg, root)


@pytest.fixture(scope="module")
def sequential_bench(rbot_synth, tmp_path_factory):
    """`jaxtrack bench` with --workers 0 (this process), lines only: (output folder, exit code, stdout)."""
    import contextlib
    import io

    from jaxtrack.cli import main

    out = tmp_path_factory.mktemp("bench") / "seq"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["bench", str(rbot_synth), "-o", str(out), "--workers", "0", "--cues", "region", "--resets", "off",
                     "--quiet"])
    return out, code, buf.getvalue()


def test_synthetic_rbot_dataset_reads_in_rbot_layout(rbot_synth):
    from jaxtrack.bench import find_items
    from jaxtrack.io import rbot_sequences, read_rbot_sequence

    assert rbot_sequences(rbot_synth) == [("box", "a_regular"), ("box", "b_dynamiclight"), ("box", "c_noisy")]
    seq = read_rbot_sequence(rbot_synth, "box", "c_noisy")
    assert seq.num_frames == 6 and seq.views[0].K[0, 0] == pytest.approx(175.0)
    regular = read_rbot_sequence(rbot_synth, "box", "a_regular")
    np.testing.assert_array_equal(seq.views[0].T_cam_obj[1], regular.views[0].T_cam_obj[1])  # one trajectory
    noisy, clean = seq.views[0].read_frame(2), regular.views[0].read_frame(2)
    assert 10 < np.std(noisy - clean) < 30  # σ = 20, clipped at 0 and 255
    items = find_items(rbot_synth)
    assert [i.name for i in items] == ["box/a_regular", "box/b_dynamiclight", "box/c_noisy"]
    assert [i.name for i in find_items(rbot_synth, variants=["c_noisy"])] == ["box/c_noisy"]
    with pytest.raises(ValueError, match=r"--objects: cat not in .* \(it has box\)"):
        find_items(rbot_synth, objects=["cat"])


def test_bcot_layout_reads_and_names_its_problems(tmp_path):
    import trimesh

    from jaxtrack.io import SequenceError, bcot_sequences, read_bcot_intrinsics, read_bcot_sequence, write_image

    root = tmp_path / "BCOT"
    (root / "models").mkdir(parents=True)
    trimesh.creation.box(extents=(80, 60, 40)).export(root / "models" / "cat.obj")
    scene = root / "light_static"
    (scene / "cat").mkdir(parents=True)
    (scene / "K.txt").write_text("Matx33f K = Matx33f(481.34025, 0.0, 329.4003, 0.0, 481.8243, 260.3788, 0.000000, "
                                 "0.000000, 1.000000);\n")
    poses = []
    for k in range(3):
        write_image(scene / "cat" / f"{k:04d}.png", np.full((48, 64, 3), 40 * k, np.uint8))
        R = trimesh.transformations.rotation_matrix(0.1 * k, [0, 1, 0])[:3, :3]
        poses.append([*R.ravel(), 5.0 * k, 0.0, 500.0])
    (scene / "cat" / "pose.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in p) for p in poses) + "\n")
    assert bcot_sequences(root) == [("light_static", "cat")]
    K = read_bcot_intrinsics(scene / "K.txt")
    np.testing.assert_allclose(K, [[481.34025, 0, 329.4003], [0, 481.8243, 260.3788], [0, 0, 1]])
    seq = read_bcot_sequence(root, "light_static", "cat")
    assert seq.num_frames == 3 and seq.views[0].frame_ids == [0, 1, 2] and seq.model_paths[1].name == "cat.obj"
    np.testing.assert_allclose(seq.views[0].T_cam_obj[1][2][:3, 3], [10.0, 0.0, 500.0])
    from jaxtrack.bench import detect_layout, find_items

    assert detect_layout(root) == "bcot"
    assert [(i.name, i.group, i.variant) for i in find_items(root)] == [("light_static/cat", "cat", "light_static")]
    # problems are named
    (scene / "cat" / "0001.png").unlink()
    with pytest.raises(SequenceError, match="0001.png is missing"):
        read_bcot_sequence(root, "light_static", "cat")
    (scene / "K.txt").write_text("1 2 3\n")
    with pytest.raises(SequenceError, match="K.txt: 3 numbers"):
        read_bcot_intrinsics(scene / "K.txt")
    with pytest.raises(SequenceError, match="no such BCOT sequence folder .*light_static/cat"):
        read_bcot_sequence(root, "light_static", "dog")


def test_a_bop_scene_with_two_objects_gives_one_bench_item_per_object(tmp_path):
    import trimesh

    from jaxtrack.bench import detect_layout, find_items
    from jaxtrack.io import write_camera_view

    seq = tmp_path / "scenes" / "seq1"
    (seq / "models").mkdir(parents=True)
    for o in (1, 2, 3):
        trimesh.creation.box(extents=(50, 50, 50)).export(seq / "models" / f"obj_{o:06d}.ply")
    T = np.eye(4)
    T[2, 3] = 400.0
    poses = {1: np.stack([T, T]), 2: np.stack([T, T]), 3: np.stack([np.full((4, 4), np.nan), T])}  # 3: no first pose
    write_camera_view(seq / "000000", np.zeros((2, 24, 32, 3), np.uint8), np.diag([30.0, 30.0, 1.0]), poses, np.eye(4))
    assert detect_layout(tmp_path / "scenes") == "bop" and detect_layout(seq) == "bop"
    items = find_items(tmp_path / "scenes")
    assert [(i.name, i.obj_id) for i in items] == [("seq1/obj_1", 1), ("seq1/obj_2", 2)]
    assert items[1].load().root == seq
    with pytest.raises(ValueError, match="not a dataset layout jaxtrack reads: RBOT needs poses_first.txt"):
        detect_layout(tmp_path)


def test_frame_steps_keep_every_sth_frame_with_its_pose(rbot_synth):
    from jaxtrack.io import frame_step_sequence, read_rbot_sequence

    seq = read_rbot_sequence(rbot_synth, "box", "a_regular")
    sub = frame_step_sequence(seq, 2)
    assert sub.num_frames == 3 and sub.views[0].frame_ids == [0, 2, 4]
    np.testing.assert_array_equal(sub.views[0].T_cam_obj[1], seq.views[0].T_cam_obj[1][::2])
    assert sub.views[0].frame_paths[1] == seq.views[0].frame_paths[2] and seq.num_frames == 6  # the original unchanged
    with pytest.raises(ValueError, match="frame step must be ≥ 1"):
        frame_step_sequence(seq, 0)


def test_auc_is_one_for_exact_poses_zero_beyond_the_range_and_monotone():
    from jaxtrack.bench import auc

    assert auc(np.zeros(5)) == pytest.approx(1.0)
    assert auc(np.full(5, 150.0)) == 0.0 and auc(np.full(3, np.nan)) == 0.0
    assert auc([50.0]) == pytest.approx(0.5, abs=2e-3)
    rng = np.random.default_rng(0)
    e = rng.uniform(0, 120, 50)
    assert auc(e) >= auc(e + 5.0)


def test_bench_writes_tables_and_resumes_without_running_again(rbot_synth, sequential_bench):
    out, code, stdout = sequential_bench
    assert code == 0, stdout
    assert "benched 3 run(s)" in stdout and "S = 1, without resets: success" in stdout
    table = (out / "bench.md").read_text()
    assert "| box | " in table and "a_regular" in table and "c_noisy" in table
    rows = (out / "bench.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("name,group,variant,step,reset")
    metrics = json.loads((out / "runs" / "box" / "a_regular" / "S1.metrics.json").read_text())
    assert metrics["frames"] == 6 and metrics["scored"] == 5 and metrics["success"] == 1.0 and metrics["error"] is None
    assert (out / "bench.png").is_file()
    before = _pose_columns(out / "runs" / "box" / "c_noisy" / "S1.csv")
    # resume: every job is found finished, nothing is tracked again
    from jaxtrack.bench import BenchSettings, run_bench

    settings = BenchSettings(cues=("region",), resets=(False,))
    again = run_bench(rbot_synth, out, settings, workers=0, progress=False)
    assert len(again.skipped) == 3 and again.executor.startswith("nothing to run")
    # a job whose results are partial (interrupted while it re-ran) is tracked again from its first frame, even with
    # an older run's figures beside them; the others are not
    csv = out / "runs" / "box" / "c_noisy" / "S1.csv"
    assert (out / "runs" / "box" / "c_noisy" / "S1.metrics.json").is_file()
    csv.write_text("\n".join(csv.read_text().splitlines()[:3]) + "\n")
    csv.with_name("S1.partial.json").write_text(json.dumps({"frames_expected": 6, "frames_written": 2}))
    resumed = run_bench(rbot_synth, out, settings, workers=0, progress=False)
    assert sorted(resumed.skipped) == ["box/a_regular S=1", "box/b_dynamiclight S=1"]
    assert _pose_columns(csv) == before and not csv.with_name("S1.partial.json").exists()
    # another cue set into the same folder is refused, naming the field
    with pytest.raises(ValueError, match="bench.json has cues = \\['region'\\], this bench \\['region', 'flow'\\]"):
        run_bench(rbot_synth, out, BenchSettings(cues=("region", "flow"), resets=(False,)), workers=0, progress=False)


def test_a_sequence_that_fails_is_reported_and_the_others_finish(rbot_synth, sequential_bench, tmp_path, capsys):
    from jaxtrack.cli import main

    broken = tmp_path / "RBOT"
    shutil.copytree(rbot_synth, broken)
    (broken / "box" / "frames" / "b_dynamiclight0003.png").unlink()
    out = tmp_path / "out"
    code = main(["bench", str(broken), "-o", str(out), "--workers", "0", "--cues", "region", "--resets", "off", "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "1 run(s) failed" in err and "box/b_dynamiclight S=1" in err
    assert "b_dynamiclight0003.png is missing" in (out / "bench.md").read_text()
    assert (out / "runs" / "box" / "c_noisy" / "S1.metrics.json").is_file()
    assert (out / "runs" / "box" / "a_regular" / "S1.metrics.json").is_file()


def test_bench_cli_refuses_bad_input(rbot_synth, tmp_path, capsys):
    from jaxtrack.cli import main

    for argv, message in (
        ([str(tmp_path / "nope")], "no such dataset folder"),
        ([str(rbot_synth), "--protocol", "bop", "--resets", "on"], "--resets: the bop protocol tracks without resets"),
        ([str(rbot_synth), "--variants", "e_fog"], "--variants: e_fog not in"),
        ([str(tmp_path)], "not a dataset layout jaxtrack reads"),
        ([str(rbot_synth), "--address", "127.0.0.1:1"], "--workers 0 runs the sequences in this process, --address"),
        ([str(rbot_synth), "--timeout-min", "1"], "--timeout-min bounds a run on Ray"),
    ):
        assert main(["bench", *argv, "-o", str(tmp_path / "o"), "--workers", "0", "--quiet"]) == 2
        assert message in capsys.readouterr().err
    for argv, message in ((["--variants", "c_noisy"], "--variants chooses the RBOT variants of --rbot"),
                          (["--rbot", "box", "--cameras", "2"], "--cameras apply to one BOP sequence"),
                          (["--rbot", "box", "--variants", "e_fog"], "RbotSynthConfig.variants must be some of")):
        assert main(["synth", str(tmp_path / "s"), *argv]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "s").exists()  # refused before anything is written


def test_tracking_writes_its_results_frame_by_frame_and_marks_a_stopped_run(rbot_synth, sequential_bench, tmp_path):
    from jaxtrack.io import read_rbot_sequence
    from jaxtrack.track import evaluate_tracking, results_state, track_sequence

    seq = read_rbot_sequence(rbot_synth, "box", "a_regular")
    csv = tmp_path / "run.csv"

    def stop_at_frame_3(record):
        if record.index == 3:
            raise KeyboardInterrupt  # as a user's Ctrl-C

    with pytest.raises(KeyboardInterrupt):
        track_sequence(seq, cues=("region",), progress=False, results=csv, on_frame=stop_at_frame_3)
    state = results_state(csv)
    assert state.state == "partial" and state.frames_written == 4 and state.frames_expected == 6
    assert len(csv.read_text().splitlines()) == 1 + 4  # header + frames 0-3, on disk
    with pytest.raises(ValueError, match="partial results: the run stopped after 4 of 6 frame"):
        evaluate_tracking(csv, seq)
    run = track_sequence(seq, cues=("region",), progress=False, results=csv)
    assert results_state(csv).state == "complete" and len(evaluate_tracking(csv, seq).im_ids) == 6
    # the same as writing the finished run afterwards
    from jaxtrack.track import write_tracking_results

    write_tracking_results(run, tmp_path / "after.csv")
    assert _pose_columns(tmp_path / "after.csv") == _pose_columns(csv)


def test_ray_local_run_equals_the_sequential_run(rbot_synth, sequential_bench, tmp_path):
    """Two local Ray workers (one XLA thread each) give the sequential run's poses, frame for frame."""
    pytest.importorskip("ray")
    from jaxtrack.bench import BenchSettings, run_bench

    out, code, _ = sequential_bench
    assert code == 0
    # single_thread=False: this process's XLA threading. The suite compiles at XLA's optimisation level 0, where one
    # thread and several round differently in the last bits and the tracking drifts apart by up to 0.3 mm; at the
    # default level the workers' single thread gives bit-identical poses (experiments/results/bench_ray.md).
    report = run_bench(rbot_synth, tmp_path / "ray", BenchSettings(cues=("region",), resets=(False,)), workers=2,
                       single_thread=False, timeout_s=240, progress=False)
    assert report.executor == "ray (1 node(s), 2 CPUs, 2 worker(s))" and not report.failed
    for variant in ("a_regular", "b_dynamiclight", "c_noisy"):
        ours = _pose_columns(tmp_path / "ray" / "runs" / "box" / variant / "S1.csv")
        assert ours == _pose_columns(out / "runs" / "box" / variant / "S1.csv"), variant

    def tables(folder):  # the success and AUC tables (the per-sequence table holds the measured times)
        return (folder / "bench.md").read_text().split("## Success rate")[1].split("## Per sequence")[0]

    assert tables(tmp_path / "ray") == tables(out)


def test_the_job_queue_keeps_a_workers_objects_and_leaves_no_worker_idle():
    from jaxtrack.bench import BenchItem, BenchJob
    from jaxtrack.bench._executor import JobQueue

    jobs = [BenchJob(BenchItem(f"{o}/{v}", "rbot", "/d", (o, v), 1, o, v), 1, False)
            for o, n in (("ape", 3), ("cat", 2), ("duck", 1)) for v in ("a", "b", "c")[:n]]
    queue = JobQueue(jobs)
    first = [queue.take(w).item.group for w in range(3)]
    assert first == ["ape", "cat", "duck"]  # each worker starts its own object, the largest first
    assert queue.take(1).item.name == "cat/b"  # worker 1 goes on with the object it has traced
    assert queue.take(2).item.name == "ape/b"  # worker 2's object is done: it takes from the largest left
    assert queue.take(0).item.name == "ape/c" and queue.take(0) is None and len(queue) == 0


def test_a_bench_past_its_timeout_reports_the_unfinished_runs_and_stops(rbot_synth, tmp_path):
    pytest.importorskip("ray")
    from jaxtrack.bench import BenchSettings, run_bench

    report = run_bench(rbot_synth, tmp_path / "late", BenchSettings(cues=("region",), resets=(False,)), workers=1,
                       single_thread=False, timeout_s=0.5, progress=False)
    assert len(report.failed) == 3 and all("timed out" in r["error"] for r in report.results)
    assert "## Failed (3)" in report.markdown.read_text()


def test_the_bop_toolkits_layout_gives_a_run_per_scene_and_object(tmp_path):
    import trimesh

    from jaxtrack.bench import detect_layout, find_items
    from jaxtrack.io import SequenceError, bop_scenes, read_bop_scene, write_camera_view

    root = tmp_path / "ycbv"
    (root / "models").mkdir(parents=True)
    for o in (1, 2):
        trimesh.creation.box(extents=(50, 50, 50)).export(root / "models" / f"obj_{o:06d}.ply")
    T = np.eye(4)
    T[2, 3] = 400.0
    write_camera_view(root / "test" / "000048", np.zeros((2, 24, 32, 3), np.uint8), np.diag([30.0, 30.0, 1.0]),
                      {1: np.stack([T, T]), 2: np.stack([T, T])}, np.eye(4))
    write_camera_view(root / "test" / "000049", np.zeros((2, 24, 32, 3), np.uint8), np.diag([30.0, 30.0, 1.0]),
                      {2: np.stack([T, T])}, np.eye(4))
    assert bop_scenes(root) == [("test", "000048"), ("test", "000049")] and detect_layout(root) == "bop"
    seq = read_bop_scene(root, "test", "000048")
    assert sorted(seq.model_paths) == [1, 2] and seq.num_frames == 2 and seq.root == root / "test" / "000048"
    items = find_items(root)
    assert [(i.name, i.obj_id, i.variant) for i in items] == [
        ("test/000048/obj_1", 1, "test/000048"), ("test/000048/obj_2", 2, "test/000048"), ("test/000049/obj_2", 2, "test/000049")]
    assert items[2].load().views[0].folder == root / "test" / "000049"
    with pytest.raises(SequenceError, match="no such BOP scene folder"):
        read_bop_scene(root, "test", "000050")
