"""Smoke versions of the paper-scene experiments (issue 12: turntable, large motion, occlusion) and the
measures they compute. The full runs write experiments/results/{turntable,large_motion,occlusion}.md.

The three --quick runs use track_presets --quick's sequence size and configuration (96x72, one camera,
region), so on the worker that already compiled that step (xdist group "tracker_quick") they compile
no new tracker program.
"""

import importlib.util
import pathlib
import sys

import equinox as eqx
import numpy as np
import pytest

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1] / "experiments"


def _load(name):
    """experiments/NAME.py as a module; its folder goes first on sys.path (once), as when it runs as a script, so its
    `import track_presets` finds the sibling."""
    if str(EXPERIMENTS) not in sys.path:
        sys.path.insert(0, str(EXPERIMENTS))
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rows(text, first_cell):
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| ") and line.strip("| ").split("|")[0].strip() == first_cell]


def _traces():
    from jaxtrack.track import track_step

    return eqx.debug.get_num_traces(track_step)


@pytest.fixture(scope="module")
def scenes_quick(tmp_path_factory):
    """The three --quick runs in one process, with the step's trace count before and after each."""
    out = tmp_path_factory.mktemp("paper_scenes")
    runs = {}
    for name in ("turntable", "large_motion", "occlusion"):
        before = _traces()
        result = _load(name).main(["--quick", "--out", str(out / f"{name}.md")])
        runs[name] = (result, (out / f"{name}.md").read_text(), before, _traces())
    return runs


# --- measures ------------------------------------------------------------------------------------------------------
def test_turntable_angles_recover_turns_past_half_a_revolution():
    turntable = _load("turntable")
    rng = np.random.default_rng(3)
    R0, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R0 *= np.sign(np.linalg.det(R0))
    angles = np.cumsum(rng.uniform(4, 16, size=50))  # beyond 360°: needs the unwrap
    angles -= angles[0]
    T = np.repeat(np.eye(4)[None], len(angles), 0)
    for k, a in enumerate(np.radians(angles)):
        c, s = np.cos(a), np.sin(a)
        T[k, :3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ R0
        T[k, :3, 3] = rng.normal(size=3) * 50  # translation does not enter the angle
    assert angles[-1] > 360
    np.testing.assert_allclose(turntable.turntable_angles(T), angles, atol=1e-9)
    # A tilt about another axis after the turn changes the full rotation but not the turn about y by much.
    tilt = np.array([[1, 0, 0], [0, np.cos(0.01), -np.sin(0.01)], [0, np.sin(0.01), np.cos(0.01)]])
    T[:, :3, :3] = tilt @ T[:, :3, :3]
    assert np.max(np.abs(turntable.turntable_angles(T) - angles)) < 0.6


def test_map_scores_counts_and_undefined_cases():
    occlusion = _load("occlusion")
    truth = np.zeros((6, 8), bool)
    truth[1:4, 2:6] = True  # 12 pixels
    same = occlusion.map_scores(truth, truth)
    assert (same["precision"], same["recall"], same["iou"]) == (1.0, 1.0, 1.0)
    shifted = np.roll(truth, 1, axis=1)  # 9 of its 12 pixels overlap the truth
    s = occlusion.map_scores(shifted, truth)
    assert (s["tp"], s["fp"], s["fn"]) == (9, 3, 3)
    assert s["precision"] == s["recall"] == 0.75 and s["iou"] == 9 / 15
    nothing = occlusion.map_scores(np.zeros_like(truth), truth)
    assert np.isnan(nothing["precision"]) and nothing["recall"] == 0.0 and nothing["iou"] == 0.0
    empty = occlusion.map_scores(np.zeros_like(truth), np.zeros_like(truth))
    assert np.isnan(empty["precision"]) and np.isnan(empty["recall"]) and np.isnan(empty["iou"])
    # Decidable: the true occluded pixels on seen surface; the recall there counts only those.
    seen = np.zeros_like(truth)
    seen[:, :4] = True  # 6 of the 12 true pixels (columns 2-3)
    d = occlusion.map_scores(shifted, truth, seen)
    assert (d["decidable"], d["tp_decidable"]) == (6, 3) and d["recall_decidable"] == 0.5  # shifted covers column 3
    assert "decidable" not in s and np.isnan(occlusion.map_scores(truth, truth, np.zeros_like(truth))["recall_decidable"])


@pytest.mark.xdist_group("tracker_quick")
def test_seen_surface_is_the_model_silhouette_where_the_appearance_model_knows_the_texel(tmp_path):
    """After `start` at the true pose the appearance model has seen part of what that frame shows: the seen pixels lie
    on the object's silhouette, its back half-turned towards the camera is unseen, and an empty model has seen nothing."""
    occlusion, tp = _load("occlusion"), _load("track_presets")
    from jaxtrack.cues.occlusion import init_appearance
    from jaxtrack.geometry import make_camera, stack_cameras
    from jaxtrack.io import load_mesh, read_sequence
    from jaxtrack.track import Tracker, TrackerConfig

    seq = read_sequence(tp.write_preset("occluded-box", tp.preset_config("occluded-box", 0.15, 2), tmp_path))
    view = seq.views[0]
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    mesh = load_mesh(seq.model_paths[1])
    tracker = Tracker(mesh, rig, config=TrackerConfig(cues=("region",)))
    T0 = np.linalg.inv(np.asarray(view.T_cam_world, np.float64)) @ np.asarray(view.T_cam_obj[1][0], np.float64)
    state = tracker.start(view.read_frame(0)[None], T0)
    seen_at = occlusion.seen_surface(tracker)
    seen = np.asarray(seen_at(state.appearance, T0))
    silhouette = occlusion.read_mask(view.folder / "object_mask" / f"{int(view.frame_ids[0]):06d}.png")  # the generator's
    grown = np.zeros_like(silhouette)  # a pixel of rasterisation either way at the edge (two renderers)
    for dy, dx in np.ndindex(3, 3):
        grown |= np.roll(np.roll(silhouette, dy - 1, 0), dx - 1, 1)
    assert seen.shape == silhouette.shape and seen.any()
    assert grown[seen].all()
    # Turned half a revolution about its own x or y axis the box shows the faces the first frame did not: unseen.
    for half_turn in (np.diag([-1.0, 1.0, -1.0, 1.0]), np.diag([1.0, -1.0, -1.0, 1.0])):  # about the box's y, x axes
        assert np.asarray(seen_at(state.appearance, T0 @ half_turn)).sum() <= 0.02 * seen.sum()
    assert not np.asarray(seen_at(init_appearance(tracker.atlas, state.appearance.texture.dtype), T0)).any()


# --- smoke runs ----------------------------------------------------------------------------------------------------
def _no_new_program(before, after):
    # At most one compile for the whole run (its frames and both rows share it: no recompilation per frame or
    # per row). With the line modality (the default for rigid objects) a smoke run on another mesh than the
    # earlier ones in this worker traces one program of its own (seen for the turntable run).
    assert after - before <= 1, (before, after)


@pytest.mark.xdist_group("tracker_quick")
def test_turntable_quick(scenes_quick):
    rows, text, before, after = scenes_quick["turntable"]
    _no_new_program(before, after)
    assert [(c, label) for c, label, _ in rows] == [("region", "box"), ("region", "box, noise")]
    for _, _, r in rows:
        assert r["frames"] == 3 and len(r["angle_true"]) == len(r["angle_est"]) == 4
        # The truth read back from scene_gt.json is the preset's 3° per frame about the turntable axis.
        np.testing.assert_allclose(r["angle_true"], 3.0 * np.arange(4), atol=1e-6)
        err = np.abs(r["angle_est"] - r["angle_true"])[1:]
        assert r["angle_err_mean"] == pytest.approx(err.mean()) and r["angle_err_max"] == pytest.approx(err.max())
        assert np.isfinite(r["rot_deg"]) and np.isfinite(r["trans_mm"])
    summary = _rows(text, "region")[0]
    assert summary[1:] == [f"{r['angle_err_mean']:.2f}" for _, _, r in rows]
    assert len(_rows(text, "box")) == 1 and len(_rows(text, "box, noise")) == 1


@pytest.mark.xdist_group("tracker_quick")
def test_large_motion_quick(scenes_quick):
    results, text, before, after = scenes_quick["large_motion"]
    _no_new_program(before, after)
    assert list(results) == ["region"] and [r["trial"] for r in results["region"]] == [0, 1]
    for r in results["region"]:
        # Without a motion cue the prediction is the frame-1 pose: its error is the motion itself (10°).
        assert r["pred_rot"] == pytest.approx(10.0, abs=1e-3)
        assert np.isfinite(r["final_rot"]) and np.isfinite(r["final_trans"])
    row = _rows(text, "region")[0]
    assert row[1] == "2" and row[2].endswith("/2)") and "(frame-1 pose)" in row[3]
    assert len(_rows(text, "0")) == 1 and len(_rows(text, "1")) == 1  # per-trial rows


@pytest.mark.xdist_group("tracker_quick")
def test_occlusion_quick(scenes_quick):
    runs, text, before, after = scenes_quick["occlusion"]
    _no_new_program(before, after)
    assert list(runs) == [("region", True)]
    r = runs[("region", True)]
    assert r["scores"][0] is None and len(r["scores"]) == 4 and len(r["rot"]) == 4 and r["rot"][0] == 0
    for k in range(1, 4):
        s, detected = r["scores"][k], r["maps"][k]
        assert detected.shape == (72, 96) and s["tp"] + s["fp"] == int(detected.sum())
        for name in ("precision", "recall", "iou"):
            assert np.isnan(s[name]) or 0 <= s[name] <= 1
    # The table lists each tracked frame with the counts of the scores.
    frames = {int(row[0]): row for row in (_rows(text, str(k))[0] for k in range(1, 4))}
    assert all(int(frames[k][1]) == r["scores"][k]["tp"] + r["scores"][k]["fn"] for k in range(1, 4))
    assert _rows(text, "region")[0][1] == "on" and "not run in --quick" in text.lower()
