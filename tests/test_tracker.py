"""The tracker: one compiled step over a sequence, statuses instead of exceptions, errors at the edge.

One small synthetic sequence (textured box, 160x120) and one compiled configuration shared by the
tests (module fixtures), so the suite pays the step's compilation once.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.geometry import make_transform, rotation_error_deg, so3_exp
from jaxtrack.render import make_mesh
from jaxtrack.track import Tracker, TrackerConfig


@pytest.fixture(scope="module")
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


@pytest.fixture(scope="module")
def tracker(sequence):
    return Tracker(sequence["mesh"], sequence["camera"], config=TrackerConfig())


@pytest.fixture(scope="module")
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
    reason="contour, flow and SIFT rows leave a depth + out-of-plane rotation combination weakly observed on this "
    "small textured box, and the region refinement creeps along it (issue 9 notes); measured 2.7° rotation error "
    "after the first frame at 160x120",
)
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


def test_one_compilation_per_crop_class(tracked):
    _, traces, crop_classes, _ = tracked
    assert traces == len(crop_classes)


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
