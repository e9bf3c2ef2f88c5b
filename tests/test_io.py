"""BOP sequence I/O, results CSV, mesh loading; the tea-box sequence renders onto the box."""

import json

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.io import (
    SequenceError,
    load_mesh,
    read_bop_results,
    read_sequence,
    write_bop_results,
    write_camera_view,
)
from jaxtrack.render import Renderer, box_mesh


def _write_small_sequence(root, frames=3):
    (root / "models").mkdir(parents=True)
    box = box_mesh((60, 40, 30))
    import trimesh

    trimesh.Trimesh(np.asarray(box.vertices), np.asarray(box.faces)).export(root / "models" / "obj_000001.ply")
    K = np.array([[500, 0, 159.5], [0, 500, 119.5], [0, 0, 1.0]])
    poses = np.stack([np.eye(4)] * frames)
    poses[:, 2, 3] = 400 + 10 * np.arange(frames)
    images = np.full((frames, 240, 320, 3), 90, np.uint8)
    write_camera_view(root / "000000", images, K, {1: poses})
    return K, poses


def test_sequence_round_trip(tmp_path):
    K, poses = _write_small_sequence(tmp_path)
    seq = read_sequence(tmp_path)
    assert seq.num_frames == 3 and list(seq.model_paths) == [1]
    view = seq.views[0]
    np.testing.assert_allclose(view.K, K)
    np.testing.assert_allclose(view.T_cam_obj[1], poses)
    assert (view.width, view.height) == (320, 240)
    assert view.read_frame(1).shape == (240, 320, 3)
    mesh = load_mesh(seq.model_paths[1])
    assert mesh.num_faces == 12


def test_sequence_errors_name_the_problem(tmp_path):
    with pytest.raises(SequenceError, match="not a directory"):
        read_sequence(tmp_path / "nope")
    _write_small_sequence(tmp_path)
    (tmp_path / "000000" / "scene_gt.json").write_text("{not json")
    with pytest.raises(SequenceError, match="scene_gt.json: malformed JSON"):
        read_sequence(tmp_path)
    (tmp_path / "000000" / "scene_gt.json").write_text(json.dumps({"0": [{"obj_id": 1, "cam_R_m2c": [1, 0], "cam_t_m2c": [0, 0, 1]}]}))
    with pytest.raises(SequenceError, match="cam_R_m2c"):
        read_sequence(tmp_path)
    gt = {str(i): [{"obj_id": 1, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 0, 400]}] for i in range(5)}
    (tmp_path / "000000" / "scene_gt.json").write_text(json.dumps(gt))
    with pytest.raises(SequenceError, match="5 frames of ground truth for 3 images"):
        read_sequence(tmp_path)
    (tmp_path / "000000" / "scene_camera.json").unlink()
    with pytest.raises(SequenceError, match="scene_camera.json: missing"):
        read_sequence(tmp_path)


def test_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        load_mesh(tmp_path / "missing.ply")
    bad = tmp_path / "points.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n")
    with pytest.raises(ValueError, match="no faces|no triangle"):
        load_mesh(bad)


def test_bop_results_round_trip(tmp_path):
    T = np.asarray(jt.se3_exp(jnp.array([1.0, 2.0, 300.0, 0.1, -0.2, 0.3])), np.float64)
    write_bop_results(tmp_path / "r.csv", [(1, 0, 1, 0.9, T, 0.01), (1, 1, 1, 0.8, T, 0.02)])
    rows = read_bop_results(tmp_path / "r.csv")
    assert [r[:4] for r in rows] == [(1, 0, 1, 0.9), (1, 1, 1, 0.8)]
    np.testing.assert_allclose(rows[1][4], T, atol=1e-6)
    (tmp_path / "bad.csv").write_text("a,b\n")
    with pytest.raises(SequenceError, match="header"):
        read_bop_results(tmp_path / "bad.csv")


def test_teabox_model_covers_the_box_at_ground_truth(shared_data):
    seq = read_sequence(shared_data / "sequences" / "visp_teabox")
    view = seq.views[0]
    assert seq.num_frames == 49 and (view.width, view.height) == (640, 480)
    mesh = load_mesh(seq.model_paths[1])
    cam = jt.make_camera(view.K, view.width, view.height)
    renderer = Renderer(mesh, cam)
    ious = []
    for frame in (0, 12, 24, 36, 48):
        img = view.read_frame(frame).astype(np.uint8)
        # The box is the textured object on a uniform grey background: threshold the colour distance
        # to the background colour (median of the border), keep the largest blob and, since a box's
        # silhouette is convex, fill it to its convex hull (dark texture patches match the grey).
        border = np.concatenate([img[:5].reshape(-1, 3), img[-5:].reshape(-1, 3), img[:, :5].reshape(-1, 3), img[:, -5:].reshape(-1, 3)])
        dist = np.linalg.norm(img.astype(float) - np.median(border, axis=0), axis=-1)
        mask = (dist > 12).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
        blob = (labels == (1 + np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
        hull = cv2.convexHull(cv2.findNonZero(blob))
        box = cv2.fillConvexPoly(np.zeros_like(blob), hull, 1).astype(bool)
        sil = np.asarray(renderer(view.T_cam_obj[1][frame]).silhouette)
        ious.append((sil & box).sum() / (sil | box).sum())
    assert min(ious) >= 0.9, ious
