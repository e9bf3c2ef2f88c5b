"""BOP sequence I/O, results CSV, mesh loading; the tea-box sequence renders onto the box."""

import json
import os

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
        _n, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
        blob = (labels == (1 + np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
        hull = cv2.convexHull(cv2.findNonZero(blob))
        box = cv2.fillConvexPoly(np.zeros_like(blob), hull, 1).astype(bool)
        sil = np.asarray(renderer(view.T_cam_obj[1][frame]).silhouette)
        ious.append((sil & box).sum() / (sil | box).sum())
    assert min(ious) >= 0.9, ious


def _gt_entry(T, obj_id=1):
    return [{"obj_id": obj_id, "cam_R_m2c": np.asarray(T)[:3, :3].ravel().tolist(), "cam_t_m2c": np.asarray(T)[:3, 3].tolist()}]


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def test_ground_truth_pairs_with_images_by_id_and_ids_may_have_gaps(tmp_path):
    _K, poses = _write_small_sequence(tmp_path, frames=4)
    cam = tmp_path / "000000"
    # Drop frame 1 everywhere: ids 0, 2, 3 remain (legal in BOP); poses must follow their ids.
    (cam / "rgb" / "000001.png").unlink()
    for name in ("scene_gt.json", "scene_camera.json"):
        _edit_json(cam / name, lambda d: d.pop("1"))
    view = read_sequence(tmp_path).views[0]
    assert view.frame_ids == [0, 2, 3]
    assert [p.name for p in view.frame_paths] == ["000000.png", "000002.png", "000003.png"]
    np.testing.assert_allclose(view.T_cam_obj[1], poses[[0, 2, 3]])
    # Images without ground truth are legal: their poses are unknown (NaN), the others stay in place.
    _edit_json(cam / "scene_gt.json", lambda d: d.pop("2"))
    view = read_sequence(tmp_path).views[0]
    assert np.isnan(view.T_cam_obj[1][1]).all()
    np.testing.assert_allclose(view.T_cam_obj[1][[0, 2]], poses[[0, 3]])


def test_a_missing_image_is_named_not_shifted_over(tmp_path):
    _write_small_sequence(tmp_path, frames=4)
    (tmp_path / "000000" / "rgb" / "000002.png").unlink()
    with pytest.raises(SequenceError, match="scene_camera.json: .*no image for frame\\(s\\) 2 .*missing 000002.png"):
        read_sequence(tmp_path)
    _edit_json(tmp_path / "000000" / "scene_camera.json", lambda d: d.pop("2"))
    with pytest.raises(SequenceError, match="scene_gt.json: 4 frames of ground truth for 3 images.*missing 000002.png"):
        read_sequence(tmp_path)


def test_first_frame_is_the_smallest_id(tmp_path):
    _, poses = _write_small_sequence(tmp_path, frames=3)
    cam = tmp_path / "000000"
    (cam / "rgb" / "000000.png").unlink()
    for name in ("scene_gt.json", "scene_camera.json"):
        _edit_json(cam / name, lambda d: d.pop("0"))
    view = read_sequence(tmp_path).views[0]
    assert view.frame_ids == [1, 2]
    np.testing.assert_allclose(view.T_cam_obj[1][0], poses[1])
    _edit_json(cam / "scene_gt.json", lambda d: d.pop("1"))
    with pytest.raises(SequenceError, match="scene_gt.json: no entry for frame 1 \\(the initial pose; first image 000001.png\\)"):
        read_sequence(tmp_path)


def test_frames_of_another_size_are_named(tmp_path):
    _write_small_sequence(tmp_path)
    odd = tmp_path / "000000" / "rgb" / "000002.png"
    cv2.imwrite(str(odd), np.zeros((120, 160, 3), np.uint8))
    with pytest.raises(SequenceError, match="000002.png: 160x120 pixels, but frame 0 \\(000000.png\\) is 320x240"):
        read_sequence(tmp_path)


def test_calibration_and_rotations_are_validated_by_file_and_field(tmp_path):
    _write_small_sequence(tmp_path)
    cam = tmp_path / "000000"
    original = {name: (cam / name).read_text() for name in ("scene_camera.json", "scene_gt.json")}

    def expect(name, edit, message):
        for n, text in original.items():
            (cam / n).write_text(text)
        _edit_json(cam / name, edit)
        with pytest.raises(SequenceError, match=message):
            read_sequence(tmp_path)

    def set_field(frame, key, value, obj=None):
        def edit(d):
            (d[frame][obj] if obj is not None else d[frame])[key] = value
        return edit

    K2 = [[510.0, 0, 159.5], [0, 500, 119.5], [0, 0, 1]]
    expect("scene_camera.json", set_field("2", "cam_K", np.ravel(K2).tolist()),
           "scene_camera.json: frame 2 field 'cam_K' .* differs from frame 0's")
    expect("scene_camera.json", set_field("0", "cam_K", [0.0] * 9), "scene_camera.json: frame 0 field 'cam_K' must have focal lengths")
    expect("scene_camera.json", set_field("1", "cam_K", [500, 0, 10, 0, 500, 10, 0, 0, 0]), "frame 1 field 'cam_K' must be upper triangular")
    expect("scene_camera.json", set_field("1", "cam_K", [500, 0, 10]), "frame 1 field 'cam_K' must hold 9 values")
    expect("scene_camera.json", set_field("0", "cam_R_w2c", [1, 0, 0, 0, 1, 0, 0, 0, -1]),
           "scene_camera.json: frame 0 field 'cam_R_w2c' is not a rotation matrix")
    expect("scene_camera.json", set_field("1", "cam_t_w2c", [0, "x", 0]), "frame 1 field 'cam_t_w2c' must be numeric")
    expect("scene_gt.json", set_field("1", "cam_R_m2c", (2 * np.eye(3)).ravel().tolist(), obj=0),
           "scene_gt.json: frame 1 object 1 field 'cam_R_m2c' is not a rotation matrix")
    expect("scene_gt.json", set_field("1", "cam_t_m2c", [0, 0, None], obj=0), "frame 1 object 1 field 'cam_t_m2c' must be finite")
    expect("scene_gt.json", lambda d: d["1"].append(d["1"][0]), "frame 1 has two instances of obj_id 1")
    expect("scene_gt.json", lambda d: d.update({"x1": []}), "scene_gt.json: key 'x1' is not a frame id")
    expect("scene_gt.json", set_field("2", "obj_id", 7, obj=0), "obj_id 7 has no mesh models/obj_000007")
    expect("scene_gt.json", lambda d: d.update({"1": {"obj_id": 1}}), "frame 1 must hold a list of objects")
    expect("scene_camera.json", lambda d: d.pop("1"), "scene_camera.json: no entry for frame 1 \\(000001.png\\)")


def test_read_frame_names_an_unreadable_image(tmp_path):
    _write_small_sequence(tmp_path)
    view = read_sequence(tmp_path).views[0]
    view.frame_paths[1].write_bytes(b"not a png")
    with pytest.raises(SequenceError, match="000001.png: cannot read image"):
        view.read_frame(1)
    cv2.imwrite(str(view.frame_paths[2]), np.zeros((10, 10), np.uint8))
    with pytest.raises(SequenceError, match="000002.png: 10x10 pixels, the camera's frames are 320x240"):
        view.read_frame(2)
    with pytest.raises(IndexError, match="frame index 5 out of range"):
        view.read_frame(5)


def test_image_reader_and_writer(tmp_path):
    from jaxtrack.io import read_image, write_image

    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    path = write_image(tmp_path / "new" / "deeper" / "a.png", rgb)  # parent folders are created
    assert read_image(path)[0, 0].tolist() == [200, 0, 0]
    assert read_image(path, "rgb", np.float32).dtype == np.float32
    assert read_image(path, "grey").shape == (6, 8)
    write_image(tmp_path / "g.png", rgb[..., 0])
    assert read_image(tmp_path / "g.png", "native").shape == (6, 8)
    assert read_image(tmp_path / "g.png", "rgb").shape == (6, 8, 3)
    with pytest.raises(FileNotFoundError, match="missing.png: image file not found"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(ValueError, match="bad.png: cannot read image"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(ValueError, match="mode must be one of"):
        read_image(path, "bgr")
    with pytest.raises(ValueError, match="no image writer for extension ''"):
        write_image(tmp_path / "noext", rgb)
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(ValueError, match="dir.png is a folder"):
        write_image(tmp_path / "dir.png", rgb)
    with pytest.raises(ValueError, match="g.png is a file"):
        write_image(tmp_path / "g.png" / "x.png", rgb)
    with pytest.raises(ValueError, match="must be uint8 or uint16"):
        write_image(tmp_path / "f.png", rgb.astype(np.float32))
    with pytest.raises(ValueError, match="must be \\(H, W\\) or \\(H, W, 3\\)"):
        write_image(tmp_path / "f.png", np.zeros((4, 4, 2), np.uint8))


def test_writers_validate_and_create_folders(tmp_path):
    T = np.eye(4)
    out = write_bop_results(tmp_path / "results" / "r.csv", [(1, 0, 1, 0.5, T, 0.1)])
    assert out.is_file() and len(read_bop_results(out)) == 1
    with pytest.raises(ValueError, match="write_bop_results: path: .* is a folder"):
        write_bop_results(tmp_path / "results", [])
    with pytest.raises(ValueError, match="row 0 T must be \\(4, 4\\)"):
        write_bop_results(tmp_path / "r2.csv", [(1, 0, 1, 0.5, np.eye(3), 0.1)])
    with pytest.raises(ValueError, match="row 0 must be"):
        write_bop_results(tmp_path / "r2.csv", [(1, 0, 1, T, 0.1)])
    images = np.zeros((2, 8, 8, 3))
    with pytest.raises(ValueError, match="T_cam_obj\\[1\\] must be \\(2, 4, 4\\) for 2 images"):
        write_camera_view(tmp_path / "cam", images, np.eye(3), {1: np.stack([T] * 3)})
    with pytest.raises(ValueError, match="write_camera_view: K must have focal lengths"):
        write_camera_view(tmp_path / "cam", images, np.zeros((3, 3)), {1: np.stack([T] * 2)})
    with pytest.raises(ValueError, match="images must be \\(N, H, W\\)"):
        write_camera_view(tmp_path / "cam", np.zeros((8, 8)), np.eye(3), {})
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="file exists and is not a folder"):
        write_camera_view(tmp_path / "file", images, np.eye(3), {})


def test_bop_results_reader_names_the_line(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,0,1,0.5,1 0 0 0 1 0 0 0 1,0 0 1,0.1\n1,x,1,0.5,1 0 0 0 1 0 0 0 1,0 0 1,0.1\n")
    with pytest.raises(SequenceError, match="r.csv:3: malformed number"):
        read_bop_results(path)
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,0,1,0.5,2 0 0 0 1 0 0 0 1,0 0 1,0.1\n")
    with pytest.raises(SequenceError, match="r.csv:2: R is not a rotation"):
        read_bop_results(path)


def test_mesh_loader_names_empty_and_unreadable_files(tmp_path):
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.ply: mesh file is empty"):
        load_mesh(tmp_path / "empty.ply")
    (tmp_path / "cut.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\n")
    with pytest.raises(ValueError, match="cut.ply: "):
        load_mesh(tmp_path / "cut.ply")
    with pytest.raises(FileNotFoundError, match="it is a folder"):
        load_mesh(tmp_path)
    _write_small_sequence(tmp_path / "seq")
    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        load_mesh(tmp_path / "seq" / "models" / "obj_000001.ply", scale=0.0)


def test_io_loads_opencv_and_trimesh_lazily():
    """`import jaxtrack` (and the .flo functions, and the tracker) must not import OpenCV, trimesh or embree, nor
    optimistix and lineax (the pose solver's reference backend, imported when a solve asks for it)."""
    import subprocess
    import sys

    code = (
        "import sys, jaxtrack, jaxtrack.io, jaxtrack.track\n"
        "from jaxtrack.io import read_flo\n"
        "from jaxtrack.synth import demo_chain\n"
        "heavy = [m for m in ('cv2', 'trimesh', 'embreex', 'skimage', 'optimistix', 'lineax') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "from jaxtrack.io import read_sequence\n"
        "assert callable(read_sequence) and jaxtrack.io.load_mesh and 'read_image' in dir(jaxtrack.io)\n"
        "assert jaxtrack.synth.PRESETS and {'cv2', 'trimesh'} <= set(sys.modules)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_outputs_on_a_file_system_that_cannot_be_written_are_refused_before_the_work(tmp_path):
    """Permission bits do not tell a virtual or read-only file system (root may 'write' anywhere): the output is
    opened before the work starts, and removed again when the probe created it."""
    import pathlib

    from jaxtrack.io import prepare_output_file, prepare_output_folder

    virtual = pathlib.Path("/proc/self/jaxtrack-results.csv")
    if pathlib.Path("/proc/self").is_dir():
        with pytest.raises(ValueError, match=r"-o/--out: cannot write /proc/self/jaxtrack-results\.csv"):
            prepare_output_file(virtual, "-o/--out")
    out = prepare_output_file(tmp_path / "sub" / "r.csv", "-o/--out")
    assert out.parent.is_dir() and not out.exists()  # the probe leaves nothing behind
    (tmp_path / "kept.csv").write_text("old")
    prepare_output_file(tmp_path / "kept.csv", "-o/--out")
    assert (tmp_path / "kept.csv").read_text() == "old"
    folder = prepare_output_folder(tmp_path / "frames", "--video")
    assert folder.is_dir() and not any(folder.iterdir())


def test_mesh_geometry_is_cached_by_content_and_read_back_without_trimesh(tmp_path, monkeypatch):
    """`load_mesh_arrays` keeps what trimesh read, keyed by the file's bytes and the scale: a new process reads the
    entry without importing trimesh (a second of a warm start); a changed file or another scale is read again."""
    import subprocess
    import sys

    import trimesh

    from jaxtrack.io import load_mesh_arrays, mesh_cache_dir

    monkeypatch.setenv("JAXTRACK_MESH_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(60, 40, 30)).export(path)
    vertices, faces = load_mesh_arrays(path)
    read = trimesh.load(str(path), process=False)
    np.testing.assert_array_equal(vertices, read.vertices)
    np.testing.assert_array_equal(faces, read.faces)
    assert vertices.dtype == np.float64 and faces.dtype == np.int64
    assert len(list(mesh_cache_dir().glob("mesh-*.npz"))) == 1
    code = ("import sys, numpy as np\nfrom jaxtrack.io import load_mesh\n"
            f"m = load_mesh({str(path)!r})\n"
            "assert 'trimesh' not in sys.modules, 'the cached mesh imported trimesh'\n"
            "np.save(sys.argv[1], np.asarray(m.vertices, np.float64))\n")
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "v.npy")], check=True, timeout=120,
                   env=dict(os.environ, JAXTRACK_MESH_CACHE=str(tmp_path / "cache")))
    np.testing.assert_allclose(np.load(tmp_path / "v.npy"), vertices.astype(np.float32))
    doubled, _ = load_mesh_arrays(path, scale=2.0)  # another scale: another entry
    np.testing.assert_allclose(doubled, 2.0 * vertices)
    trimesh.creation.box(extents=(10, 20, 30)).export(path)  # the same name, other bytes
    changed, _ = load_mesh_arrays(path)
    np.testing.assert_allclose(np.ptp(changed, axis=0), (10, 20, 30))
    assert len(list(mesh_cache_dir().glob("mesh-*.npz"))) == 3
    for damage in (b"", b"PK\x03\x04 not a zip", None):  # empty, garbled, a valid .npz of no mesh: removed, read again
        entry = next(e for e in mesh_cache_dir().glob("mesh-*.npz") if np.allclose(np.ptp(np.load(e)["vertices"], 0), (10, 20, 30)))
        if damage is None:
            np.savez(entry, vertices=np.zeros(3), faces=np.zeros((1, 3), int))
        else:
            entry.write_bytes(damage)
        np.testing.assert_array_equal(load_mesh_arrays(path)[0], changed)
        np.testing.assert_array_equal(load_mesh_arrays(path)[0], changed)  # from the entry made again
    monkeypatch.setenv("JAXTRACK_MESH_CACHE", "0")
    assert mesh_cache_dir() is None
    trimesh.creation.box(extents=(5, 5, 5)).export(path)
    np.testing.assert_allclose(np.ptp(load_mesh_arrays(path)[0], axis=0), (5, 5, 5))
    assert len(list((tmp_path / "cache").glob("mesh-*.npz"))) == 3  # nothing kept


def test_keyframe_rays_hit_where_trimesh_embree_intersector_does():
    """`MeshRays` (embree without trimesh) gives trimesh's first hits: the same rays, the same points."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    from jaxtrack.track._keyframes import MeshRays

    rng = np.random.default_rng(0)
    for tm in (trimesh.creation.torus(40.0, 12.0), trimesh.creation.box(extents=(60, 40, 30))):
        origins = rng.normal(size=(500, 3)) * 20 + np.array([0.0, 0.0, 300.0])
        directions = rng.uniform(-0.6, 0.6, (500, 3)) * tm.extents - origins
        loc, ray, _ = RayMeshIntersector(tm).intersects_location(origins, directions, multiple_hits=False)
        ours, ours_ray = MeshRays(tm.vertices, tm.faces).first_hits(origins, directions)
        assert 100 < len(ray) < 500
        np.testing.assert_array_equal(np.sort(ours_ray), np.sort(ray))
        np.testing.assert_allclose(ours[np.argsort(ours_ray)], loc[np.argsort(ray)], atol=1e-9)
    # Rays skimming a face of the box: embree's float32 hits there are dropped as trimesh drops them, and every hit kept
    # lies on the surface.
    box = trimesh.creation.box(extents=(60, 40, 30))
    slope = 10.0 ** rng.uniform(-9, -3, 4000)
    origins = np.stack([rng.uniform(-40, -31, 4000), rng.uniform(-19, 19, 4000), np.full(4000, 15.0) + rng.uniform(-1e-3, 1e-3, 4000)], 1)
    directions = np.stack([np.ones(4000), np.zeros(4000), -slope], 1)
    loc, ray, _ = RayMeshIntersector(box).intersects_location(origins, directions, multiple_hits=False)
    ours, ours_ray = MeshRays(box.vertices, box.faces).first_hits(origins, directions)
    assert len(ours_ray) <= len(ray) + 4  # no more than a few where embree's two runs round differently
    assert np.abs(box.nearest.signed_distance(ours)).max() < 1e-3
    with pytest.raises(ValueError, match="origins and directions must both be"):
        MeshRays(box.vertices, box.faces).first_hits(origins, directions[:3])
