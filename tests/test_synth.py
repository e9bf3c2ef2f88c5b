"""Synthetic sequences: deterministic, exact ground truth, cross-checked against the JAX renderer."""

import dataclasses
import itertools

import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.cli import main as cli_main
from jaxtrack.geometry import rotation_error_deg
from jaxtrack.io import read_sequence
from jaxtrack.render import Renderer, make_mesh
from jaxtrack.synth import (
    PRESETS,
    SynthConfig,
    camera_ring,
    demo_chain,
    look_at,
    perturb_pose,
    project_model_points,
    random_pose_scene,
    render_sequence,
)


def _small(cfg, **kw):
    return dataclasses.replace(cfg, **{"frames": 3, "width": 320, "height": 240, "focal": 350.0, **kw})


def test_deterministic_given_seed():
    cfg = _small(SynthConfig(noise_sigma=20, occluders=1, seed=3))
    a, b = render_sequence(cfg), render_sequence(cfg)
    np.testing.assert_array_equal(a["images"][0], b["images"][0])
    np.testing.assert_array_equal(a["T_cam_obj"][0], b["T_cam_obj"][0])
    c = render_sequence(dataclasses.replace(cfg, seed=4))
    assert not np.array_equal(a["T_cam_obj"][0], c["T_cam_obj"][0])


@pytest.mark.parametrize("preset", ["teabox-large-motion", "turntable-teapot", "stereo-noise"])
def test_ray_caster_and_jax_renderer_agree(preset, shared_data):
    cfg = _small(PRESETS[preset])
    seq = render_sequence(cfg)
    tm = seq["mesh"]
    for c in range(cfg.cameras):
        renderer = Renderer(make_mesh(tm.vertices, tm.faces), jt.make_camera(seq["K"], cfg.width, cfg.height))
        for k in range(cfg.frames):
            sil = np.asarray(renderer(jnp.asarray(seq["T_cam_obj"][c][k], jnp.float32)).silhouette)
            ref = seq["object_mask"][c][k]
            iou = (sil & ref).sum() / (sil | ref).sum()
            assert iou >= 0.99, (preset, c, k, iou)


def test_motion_has_the_requested_step():
    cfg = _small(SynthConfig(motion="random", step_px=20, step_deg=6), frames=6)
    T = render_sequence(cfg)["T_cam_obj"][0]
    for a, b in itertools.pairwise(T):
        angle = float(rotation_error_deg(b[:3, :3], a[:3, :3]))
        assert angle == pytest.approx(6.0, abs=1e-6)
        shift_px = np.linalg.norm(b[:3, 3] - a[:3, 3]) * cfg.focal / cfg.distance
        assert shift_px == pytest.approx(20.0, rel=1e-6)


def test_occluder_masks_and_noise():
    clean = render_sequence(_small(SynthConfig(occluders=0)))
    noisy = render_sequence(_small(SynthConfig(occluders=2, noise_sigma=40)))
    diff = noisy["images"][0].astype(float) - clean["images"][0].astype(float)
    free = ~noisy["object_mask"][0] | ~noisy["occluder_mask"][0]
    assert 30 < diff[..., 0][free].std() < 50  # σ = 40 before clipping
    assert noisy["occluder_mask"][0].any()
    assert (noisy["occluder_mask"][0] <= noisy["object_mask"][0]).all()


def test_cli_writes_a_readable_bop_sequence(tmp_path, shared_data):
    rc = cli_main(["synth", "--preset", "turntable-teapot", "--frames", "2", "--quiet", str(tmp_path / "seq")])
    assert rc == 0
    seq = read_sequence(tmp_path / "seq")
    assert seq.num_frames == 2
    view = seq.views[0]
    assert np.isfinite(view.T_cam_obj[1]).all()
    assert (tmp_path / "seq" / "000000" / "occluder_mask" / "000001.png").is_file()
    assert cli_main(["synth", "--preset", "nope", str(tmp_path / "x")]) == 2


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("frames", -3, "SynthConfig.frames must be an integer ≥ 1, got -3"),
        ("frames", 2.5, "SynthConfig.frames must be an integer"),
        ("cameras", 0, "SynthConfig.cameras must be an integer in \\[1, 4\\], got 0"),
        ("occluders", True, "SynthConfig.occluders must be an integer"),
        ("width", 4, "SynthConfig.width must be an integer ≥ 8"),
        ("seed", -1, "SynthConfig.seed"),
        ("noise_sigma", -1.0, "SynthConfig.noise_sigma must be a finite number ≥ 0"),
        ("salt_fraction", 1.5, "SynthConfig.salt_fraction must lie in \\[0, 1\\]"),
        ("focal", 0.0, "SynthConfig.focal must be a finite number > 0"),
        ("size_mm", float("nan"), "SynthConfig.size_mm"),
        ("appearance", "shiny", "SynthConfig.appearance must be one of texture, photo, flat"),
        ("motion", "teleport", "SynthConfig.motion must be one of"),
        ("background", "moon", "SynthConfig.background must be one of"),
        ("colour", (1, 2), "SynthConfig.colour must be 3 numbers in \\[0, 255\\]"),
        ("object", "no/such/mesh.ply", "SynthConfig.object .*mesh file not found"),
        ("pose_file", "no/such/poses.npy", "SynthConfig.pose_file: .*pose file not found"),
    ],
)
def test_config_refuses_values_it_cannot_render(field, value, message):
    with pytest.raises(ValueError, match=message):
        SynthConfig(**{field: value})
    with pytest.raises(ValueError, match=message):  # overriding a preset goes through the same check
        dataclasses.replace(PRESETS["stereo-noise"], **{field: value})


def test_pose_file_is_validated_by_name(tmp_path):
    good = np.repeat(np.eye(4)[None], 3, 0)
    good[:, 2, 3] = 600.0
    np.save(tmp_path / "good.npy", good)
    cfg = _small(SynthConfig(motion="file", pose_file=str(tmp_path / "good.npy"), frames=3, object="box"))
    np.testing.assert_allclose(render_sequence(cfg)["T_cam_obj"][0][:, :3, :3], np.repeat(_look_at_R(cfg)[None], 3, 0) @ good[:, :3, :3])
    bad = good.copy()
    bad[1, :3, :3] *= 2.0
    np.save(tmp_path / "bad.npy", bad)
    with pytest.raises(ValueError, match="bad.npy: pose 1 rotation is not a rotation matrix"):
        render_sequence(dataclasses.replace(cfg, pose_file=str(tmp_path / "bad.npy")))
    np.save(tmp_path / "short.npy", good[:2])
    with pytest.raises(ValueError, match="short.npy: need \\(3, 4, 4\\) poses"):
        render_sequence(dataclasses.replace(cfg, pose_file=str(tmp_path / "short.npy")))
    (tmp_path / "junk.npy").write_text("junk")
    with pytest.raises(ValueError, match="junk.npy: not a .npy array file"):
        render_sequence(dataclasses.replace(cfg, pose_file=str(tmp_path / "junk.npy")))


def _look_at_R(cfg):
    from jaxtrack.synth import look_at

    return look_at([0.0, -0.35 * cfg.distance, -cfg.distance])[0]


def test_write_sequence_refuses_a_file_as_root_before_rendering(tmp_path):
    from jaxtrack.synth import write_sequence

    (tmp_path / "f").write_text("x")
    calls = []
    with pytest.raises(ValueError, match="write_sequence: root: .*f exists and is not a folder"):
        write_sequence(_small(SynthConfig(frames=1)), tmp_path / "f", progress=type("P", (), {"update": calls.append})())
    assert calls == []  # nothing was rendered


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: look_at([0.0, 0.0, 0.0]), "look_at: eye .* must differ from target"),
        (lambda: look_at([1.0, 2.0]), "look_at: eye must hold 3 values"),
        (lambda: camera_ring(0), "camera_ring: num_cameras must be an integer ≥ 1, got 0"),
        (lambda: demo_chain(3, branches=2), "demo_chain: two branches need an even num_joints"),
        (lambda: demo_chain(-1), "demo_chain: num_joints must be an integer ≥ 0"),
        (lambda: demo_chain(2, branches=3), "demo_chain: branches must be 1 or 2"),
        (lambda: random_pose_scene(0, num_points=0), "random_pose_scene: num_points must be an integer ≥ 1"),
        (lambda: random_pose_scene(0, num_points=2, model=demo_chain(3)), "num_points must be ≥ the model's 4 parts"),
        (lambda: random_pose_scene(0, noise_px=-1.0), "random_pose_scene: noise_px must be a finite number ≥ 0"),
        (lambda: random_pose_scene(-1), "random_pose_scene: seed must be an integer ≥ 0"),
        (lambda: perturb_pose(np.random.default_rng(0), np.eye(3), 0.1, 1.0), "perturb_pose: T must be a \\(4, 4\\) matrix"),
        (lambda: perturb_pose(np.random.default_rng(0), 2 * np.eye(4), 0.1, 1.0), "perturb_pose: T\\[:3, :3\\] is not a rotation"),
        (lambda: perturb_pose(np.random.default_rng(0), np.eye(4), -0.1, 1.0), "random_rotation: max_angle must be"),
        (lambda: perturb_pose(np.random.default_rng(0), np.eye(4), 0.1, np.nan), "perturb_pose: max_translation must be"),
    ],
)
def test_pose_scene_builders_name_bad_arguments(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_project_model_points_checks_the_pose_against_the_model():
    scene = random_pose_scene(0, num_points=10, model=demo_chain(2, dtype=jnp.float64), dtype=np.float64)
    with pytest.raises(ValueError, match="project_model_points: theta must hold 2 values, got 3"):
        project_model_points(scene, np.eye(4), [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="project_model_points: T_world_root must have last row"):
        project_model_points(scene, np.vstack([np.eye(4)[:3], [1.0, 0, 0, 1]]), [0.1, 0.2])
    moved = project_model_points(scene, scene.T_world_root, scene.theta)
    np.testing.assert_allclose(moved.pixel, scene.pixel, atol=1e-9)  # same pose, no noise: same pixels
