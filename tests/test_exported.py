"""Traced programs kept on disk (`jaxtrack._exported.persistent_jit`): the same outputs as `eqx.filter_jit`, a second
"process" (a fresh wrapper, nothing in memory) loads the program instead of tracing it, and every signature that
could decide another program gets its own file."""

import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack import _exported
from jaxtrack._exported import enable_exported_cache, persistent_jit

KNOWN_CODE = _exported._KNOWN_CODE


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """The exported cache on, in a fresh folder, for this test only (the suite runs with it off)."""
    monkeypatch.delenv("JAXTRACK_EXPORT_CACHE", raising=False)
    monkeypatch.setattr(_exported, "_FOLDER", [None])
    # This module's classes count as known code here (the signature cannot see test code change, nor a user's).
    monkeypatch.setattr(_exported, "_KNOWN_CODE", (*KNOWN_CODE, __name__.split(".")[0]))
    return enable_exported_cache(tmp_path / "exported")


class Scaled(eqx.Module):
    weights: jax.Array
    power: int = eqx.field(static=True)
    name: str = eqx.field(static=True, default="scaled")


TRACES = []


def model(m: Scaled, x, offset=None, factor=2.0):
    """Arrays traced, `power`, `factor` and the absence of `offset` static; returns a module, an array and a string."""
    TRACES.append(1)
    y = factor * (m.weights * x) ** m.power
    if offset is not None:
        y = y + offset
    return Scaled(y, m.power + 1, "out"), jnp.sum(y), "done"


def _files(folder):
    return sorted(p.name for p in folder.iterdir())


def test_same_outputs_as_filter_jit_and_a_fresh_wrapper_loads_instead_of_tracing(folder):
    m, x = Scaled(jnp.arange(3.0), 2), jnp.array([1.0, -2.0, 0.5])
    expected = eqx.filter_jit(model)(m, x, offset=jnp.ones(3), factor=3.0)
    first = persistent_jit(model)
    got = first(m, x, offset=jnp.ones(3), factor=3.0)
    assert first.exported == 1 and first.loaded == 0 and len(_files(folder)) == 1
    fresh = persistent_jit(model)  # a new process: nothing in memory
    del TRACES[:]
    again = fresh(m, x, offset=jnp.ones(3), factor=3.0)
    assert TRACES == [] and fresh.loaded == 1 and fresh.exported == 0
    for out in (got, again):
        assert isinstance(out[0], Scaled) and out[0].power == 3 and out[0].name == "out" and out[2] == "done"
        assert np.array_equal(np.asarray(out[0].weights), np.asarray(expected[0].weights))
        assert float(out[1]) == float(expected[1])
    # Later calls with new values of the same signature: no trace, no file.
    del TRACES[:]
    out = fresh(Scaled(jnp.ones(3), 2), 2 * x, offset=jnp.zeros(3), factor=3.0)
    assert TRACES == [] and len(_files(folder)) == 1
    assert np.allclose(np.asarray(out[0].weights), 3.0 * (2 * np.asarray(x)) ** 2)


def test_every_static_or_shape_change_is_its_own_program(folder):
    f = persistent_jit(model)
    m, x = Scaled(jnp.arange(3.0), 2), jnp.ones(3)
    outs = [f(m, x), f(Scaled(jnp.arange(3.0), 3), x), f(m, x, factor=5.0), f(m, x, offset=jnp.ones(3)),
            f(Scaled(jnp.arange(4.0), 2), jnp.ones(4)), f(Scaled(jnp.arange(3.0), 2, "other"), x),
            f(m, x.astype(jnp.float32))]
    assert f.exported == len(outs) and len(_files(folder)) == len(outs)
    fresh = persistent_jit(model)
    for args, kwargs, out in zip([(m, x), (Scaled(jnp.arange(3.0), 3), x), (m, x)], [{}, {}, {"factor": 5.0}], outs):
        assert float(fresh(*args, **kwargs)[1]) == float(out[1])
    assert fresh.loaded == 3 and fresh.exported == 0
    assert float(outs[1][1]) == float(jnp.sum(2.0 * jnp.arange(3.0) ** 3))
    assert float(outs[2][1]) == float(jnp.sum(5.0 * jnp.arange(3.0) ** 2))


def test_weak_types_run_filter_jit_and_trace_settings_are_part_of_the_signature(folder):
    f = persistent_jit(lambda a, b: a * b)
    weak = jnp.asarray(0.1)  # weakly typed: promotes to the float32 of b, as under eqx.filter_jit
    assert jax.typeof(weak).weak_type
    out = f(weak, jnp.ones(2, jnp.float32))
    assert out.dtype == eqx.filter_jit(lambda a, b: a * b)(weak, jnp.ones(2, jnp.float32)).dtype == jnp.float32
    assert f.exported == 0 and _files(folder) == []
    strong = jnp.asarray(0.1, jnp.float32)
    assert f(strong, jnp.ones(2, jnp.float32)).dtype == jnp.float32 and f.exported == 1
    g = persistent_jit(model)
    m, x = Scaled(jnp.arange(3.0), 2), jnp.ones(3)
    plain_digest = g.digest(m, x)
    with jax.default_matmul_precision("highest"):  # fixed in the program when traced
        assert g.digest(m, x) != plain_digest
    assert g.digest(m, x) == plain_digest


def test_a_program_that_fails_to_run_falls_back_for_good(folder, monkeypatch):
    f = persistent_jit(model)
    m, x = Scaled(jnp.arange(3.0), 2), jnp.ones(3)
    expected = float(f(m, x)[1])

    def broken(self, dynamic):
        raise ValueError("exported for platforms ('cpu',) but it is used on ('cuda',)")

    monkeypatch.setattr(_exported._Entry, "__call__", broken)
    with pytest.warns(RuntimeWarning, match="traced instead"):
        assert float(f(m, x)[1]) == expected
    assert float(f(m, x)[1]) == expected  # the plain path now, without a warning
    assert list(f.memory.values()) == [_exported._PLAIN]


class WithFunction(eqx.Module):
    fn: object = eqx.field(static=True)


def test_what_cannot_be_pickled_or_is_traced_runs_filter_jit(folder):
    local = persistent_jit(lambda m, x: m.fn(x))
    assert float(local(WithFunction(lambda v: 3 * v), jnp.asarray(2.0))) == 6.0  # a lambda: no signature on disk
    assert local.digest(WithFunction(lambda v: 3 * v), jnp.asarray(2.0)) is None
    assert local.exported == 0 and _files(folder) == []
    f = persistent_jit(model)
    m = Scaled(jnp.arange(3.0), 2)
    batched = jax.vmap(lambda x: f(m, x)[1])(jnp.arange(6.0).reshape(2, 3))  # under vmap: tracers, filter_jit
    assert np.allclose(np.asarray(batched), [2 * np.sum((np.arange(3.0) * r) ** 2) for r in np.arange(6.0).reshape(2, 3)])
    grad = jax.grad(lambda x: f(m, x)[1])(jnp.ones(3))
    assert np.allclose(np.asarray(grad), 4 * np.arange(3.0) ** 2)
    assert f.exported == 0 and _files(folder) == []


class UserCode(eqx.Module):
    """Stands for a user's modality: its code is outside jaxtrack, and could change under the same name."""

    weights: jax.Array

    def __call__(self, x):
        return self.weights * x


def test_user_code_in_the_signature_or_the_registry_is_not_kept(folder, monkeypatch):
    from jaxtrack.modality import _registry

    monkeypatch.setattr(_exported, "_KNOWN_CODE", KNOWN_CODE)  # as outside the tests: this module is user code
    f = persistent_jit(lambda m, x: m(x))
    assert UserCode.__module__.split(".")[0] not in _exported._KNOWN_CODE
    assert float(f(UserCode(jnp.asarray(2.0)), jnp.asarray(3.0))) == 6.0
    assert f.digest(UserCode(jnp.asarray(2.0)), jnp.asarray(3.0)) is None and _files(folder) == []
    g = persistent_jit(model)
    m, x = Scaled(jnp.arange(3.0), 2), jnp.ones(3)
    assert g.digest(m, x) is None  # Scaled is this module's
    monkeypatch.setattr(_exported, "_KNOWN_CODE", (*KNOWN_CODE, __name__.split(".")[0]))
    assert g.digest(m, x) is not None
    notebook_cue = type("NotebookCue", (), {"__module__": "__main__"})  # a modality registered from a notebook
    monkeypatch.setitem(_registry._MODALITIES, "user-cue", notebook_cue)
    assert g.digest(m, x) is not None  # registered, but not named by these arguments
    named = Scaled(jnp.arange(3.0), 2, name="user-cue")  # a configuration that names it
    assert g.digest(named, x) is None
    g(named, x)
    assert g.exported == 0 and _files(folder) == []


def test_programs_of_other_versions_are_removed_after_a_day(folder):
    stale, recent, other_function = (folder / "model-0000aaaa-1234.jaxexport", folder / "model-0000bbbb-1234.jaxexport",
                                     folder / "other-0000cccc-1234.jaxexport")
    for path in (stale, recent, other_function):
        path.write_bytes(b"x")
    day = _exported.STALE_AFTER_S
    os.utime(stale, (os.path.getatime(stale) - 2 * day, os.path.getmtime(stale) - 2 * day))
    os.utime(other_function, (os.path.getatime(stale) - 2 * day, os.path.getmtime(stale) - 2 * day))
    f = persistent_jit(model)
    f(Scaled(jnp.arange(3.0), 2), jnp.ones(3))
    kept = _files(folder)
    assert stale.name not in kept and recent.name in kept and other_function.name in kept
    (written,) = [name for name in kept if name.startswith(f"model-{_exported._environment_tag()}-")]
    assert written.endswith(f"-{f.digest(Scaled(jnp.arange(3.0), 2), jnp.ones(3))}.jaxexport")


def test_off_without_a_folder_and_a_damaged_file_is_replaced(folder, monkeypatch):
    f = persistent_jit(model)
    m, x = Scaled(jnp.arange(3.0), 2), jnp.ones(3)
    f(m, x)
    (path,) = list(folder.iterdir())
    path.write_bytes(b"not a program")
    fresh = persistent_jit(model)
    assert float(fresh(m, x)[1]) == float(f(m, x)[1]) and fresh.exported == 1 and fresh.loaded == 0
    assert path.stat().st_size > 100
    monkeypatch.setenv("JAXTRACK_EXPORT_CACHE", "0")
    assert enable_exported_cache(folder) is None
    off = persistent_jit(model)
    off(m, x)
    assert off.exported == 0 and off.loaded == 0


_DIGEST_SCRIPT = """
import os, numpy as np, jaxtrack as jt
from jaxtrack.render import make_mesh
from jaxtrack.track import Tracker, TrackerConfig
from jaxtrack.track._tracker import _track_step_jit
import trimesh
box = trimesh.creation.box((80.0, 60.0, 40.0))
cam = jt.make_camera(np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]]), 80, 60)
tracker = Tracker(make_mesh(box.vertices, box.faces), cam)  # the default configuration: lines, flow, SIFT
T = np.eye(4); T[2, 3] = 400.0
tracker._replan(np.asarray(T, np.float32), np.zeros((0,), np.float32))
tracker.prepare()  # the sparse viewpoint model: part of the signature
print("DIGEST", _track_step_jit.digest(tracker.setup(), T=np.asarray(T, np.float32)))
"""


def test_the_tracker_setups_signature_is_the_same_in_every_process():
    """String hashing is randomised per process: a signature that pickled a set of strings would differ between two
    runs, and the disk cache would never hit."""
    digests = []
    for seed in ("1", "2"):
        env = dict(os.environ, PYTHONHASHSEED=seed, JAX_PLATFORMS="cpu")
        proc = subprocess.run([sys.executable, "-c", _DIGEST_SCRIPT], check=False, capture_output=True, text=True, env=env, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        digests.append(next(line.split()[1] for line in proc.stdout.splitlines() if line.startswith("DIGEST")))
    assert digests[0] == digests[1] and digests[0] != "None"


def _small_box_scene(dtype):
    """A 3-frame textured box at 128x96 (mesh, camera, frames of `dtype`, first pose) and the tracker's kept
    programs that a new process starts without (`memory` reset by the tests)."""
    import jaxtrack as jt
    from jaxtrack.render import make_mesh
    from jaxtrack.synth import SynthConfig, render_sequence
    from jaxtrack.track import _tracker as tracker_module

    cfg = SynthConfig(object="box", appearance="photo", texture_photo="astronaut", size_mm=160, motion="random",
                      step_px=3, step_deg=1.5, frames=3, width=128, height=96, focal=140, background="coffee", seed=5)
    seq = render_sequence(cfg)
    mesh, camera = make_mesh(seq["mesh"].vertices, seq["mesh"].faces), jt.make_camera(seq["K"], 128, 96)
    kept = (tracker_module._track_step_jit, tracker_module._start_frame_jit, tracker_module._initial_modality_states,
            tracker_module._initial_appearance_jit)
    return mesh, camera, seq["images"][0].astype(dtype), seq["T_cam_obj"][0][0], kept


def test_a_tracker_with_the_cache_tracks_as_without_and_a_new_process_traces_nothing(folder, monkeypatch):
    """With SIFT (a modality that reads host inputs) and a kept, asynchronously dispatched program, `Tracker.step`
    runs `start_frame` (crops, render at χ_t) as a program of its own while the host matches keypoints, then
    `track_step(early=)`: the poses equal those of the one program `eqx.filter_jit` runs without the cache. With XLA's
    default emitters (the product's; the suite's older ones, $JAXTRACK_FUSION_EMITTERS=0, round the split programs
    differently: 1.2e-4 in the pose matrix here)."""
    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "1")
    from jaxtrack.track import Tracker, TrackerConfig
    from jaxtrack.track import _tracker as tracker_module
    from jaxtrack.track._step import track_step

    mesh, camera, images, T0, kept = _small_box_scene(np.float32)
    for wrapped in kept:  # as in a new process
        monkeypatch.setattr(wrapped, "memory", {})
    monkeypatch.setattr(os, "cpu_count", lambda: 2)  # a core left for the device beside the one camera's detection

    def run():
        tracker = Tracker(mesh, camera, config=TrackerConfig(cues=("region", "sift")))
        state = tracker.start(images[0], T0)
        poses = []
        for k in (1, 2):
            state, result, _ = tracker.step(state, images[k])
            poses.append(np.asarray(result.T_world_root))
        return np.stack(poses)

    monkeypatch.setattr(_exported, "_FOLDER", [None])
    plain = run()  # eqx.filter_jit: one program after the host
    assert not tracker_module._start_frame_jit.memory
    monkeypatch.setattr(_exported, "_FOLDER", [folder])
    with_cache = run()
    assert {"track_step", "start_frame"} <= {name.split("-")[0] for name in _files(folder)}
    # A new process: nothing in memory; the step, its start, the modality states and the appearance come from the folder.
    for wrapped in kept:
        monkeypatch.setattr(wrapped, "memory", {})
        monkeypatch.setattr(wrapped, "loaded", 0)
    before = eqx.debug.get_num_traces(track_step)
    again = run()
    assert eqx.debug.get_num_traces(track_step) == before
    assert all(wrapped.loaded == 1 for wrapped in kept[:3])
    assert np.array_equal(with_cache, again)
    assert np.allclose(plain, with_cache, rtol=0, atol=1e-9), np.abs(plain - with_cache).max()


def test_compiled_ahead_in_threads_the_calls_compile_nothing(folder):
    """`persistent_jit.compile` makes the entry and compiles its program without running it, and the call then finds
    it in jit's cache (`Tracker.step` compiles `start_frame` in a thread while it compiles `track_step` on zeros
    shaped as `start_frame`'s outputs, `outputs_like`). XLA's on-disk cache is off here: every compile is counted."""
    from jax._src import dispatch, monitoring

    compiles = []

    def count(event, seconds, **kwargs):
        if event == dispatch.BACKEND_COMPILE_EVENT:
            compiles.append(seconds)

    m, x = Scaled(jnp.arange(3.0), 2), jnp.array([1.0, -2.0, 0.5])
    produce, consume = persistent_jit(model), persistent_jit(lambda s, total: s.weights * total)
    like = produce.outputs_like(m, x)  # its entry now exists: traced and exported
    assert isinstance(like[0], Scaled) and like[0].power == 3 and like[2] == "done"
    assert like[0].weights.shape == (3,) and not np.any(like[0].weights) and like[1].shape == ()
    cache_was = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    monitoring.register_event_duration_secs_listener(count)
    try:
        import threading

        thread = threading.Thread(target=produce.compile, args=(m, x))
        thread.start()
        assert consume.compile(like[0], like[1])
        thread.join()
        compiled = len(compiles)
        out = produce(m, x)
        got = consume(out[0], out[1])
        assert len(compiles) == compiled == 2  # one compile per program, none at the calls
    finally:
        monitoring.unregister_event_duration_listener(count)
        jax.config.update("jax_enable_compilation_cache", cache_was)
    expected = eqx.filter_jit(model)(m, x)
    assert np.array_equal(np.asarray(got), np.asarray(expected[0].weights * expected[1]))
    _exported._FOLDER[0] = None  # without a folder: nothing compiled ahead (eqx.filter_jit compiles at the call)
    assert produce.outputs_like(m, x) is None and produce.compile(m, x) is False


def test_the_first_step_compiled_from_start_on_is_the_one_the_step_runs(folder, monkeypatch):
    """`Tracker.start` compiles the first step's programs in a background thread (`_start_precompile`): shapes from the
    start programs' entries, the host inputs' from an empty region. The step then compiles nothing of its own: as many
    XLA compiles and traces of `track_step` as with the precompile off, and the same poses (a signature guessed wrong
    would compile twice), and both programs are compiled before the step runs. XLA's on-disk cache is off: every
    compile is counted. Inside a thread-local jax setting the thread compiles nothing (it would compile another
    program) and the step compiles as before."""
    from jax._src import dispatch, monitoring

    from jaxtrack.track import Tracker, TrackerConfig
    from jaxtrack.track._step import track_step

    mesh, camera, images, T0, kept = _small_box_scene(np.uint8)
    monkeypatch.setattr(os, "cpu_count", lambda: 2)  # one camera, two cores: start_frame beside track_step
    compiles = []

    def count(event, seconds, **kwargs):
        if event == dispatch.BACKEND_COMPILE_EVENT:
            compiles.append(seconds)

    def run(precompile: bool):
        for wrapped in kept:  # as in a new process
            monkeypatch.setattr(wrapped, "memory", {})
        compiles.clear()
        traces = eqx.debug.get_num_traces(track_step)
        tracker = Tracker(mesh, camera, config=TrackerConfig(cues=("region", "sift")))
        tracker.precompile_first_step = precompile
        state = tracker.start(images[0], T0)
        assert (tracker._precompile is not None) == precompile
        if precompile:  # done before the first step: both programs compiled, not left to the step's calls
            tracker.join_background()
            entries = [*kept[0].memory.values(), *kept[1].memory.values()]
            assert len(entries) == 2 and all(entry.compiled for entry in entries)
        poses = []
        for k in (1, 2):
            state, result, _ = tracker.step(state, images[k])
            poses.append(np.asarray(result.T_world_root))
        return np.stack(poses), len(compiles), eqx.debug.get_num_traces(track_step) - traces

    cache_was = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    monitoring.register_event_duration_secs_listener(count)
    try:
        run(False)  # the small programs outside `kept` (boxes, raster plans) compile once, here
        off = run(False)
        on = run(True)
    finally:
        monitoring.unregister_event_duration_listener(count)
        jax.config.update("jax_enable_compilation_cache", cache_was)
    assert np.array_equal(on[0], off[0])
    assert on[1:] == off[1:], (on[1:], off[1:])  # (compiles, track_step traces)
    tracker = Tracker(mesh, camera, config=TrackerConfig(cues=("region", "sift")))
    with jax.default_matmul_precision("float32"):  # seen by this thread only
        tracker.start(images[0], T0)
        tracker.join_background()
        assert not tracker._compiled  # the thread did not compile under other settings; the step will


def test_dispatches_async_only_for_kept_programs(folder, monkeypatch):
    double = persistent_jit(lambda x: 2.0 * x)
    x = jnp.ones((3,), jnp.float32)
    assert double.dispatches_async(x)
    assert not double.dispatches_async(jnp.asarray(1.0))  # weakly typed: eqx.filter_jit
    monkeypatch.setattr(_exported, "_FOLDER", [None])
    assert not double.dispatches_async(x)


_EAGER_SCRIPT = """
import logging, numpy as np, jax, jax.numpy as jnp
names = []
class Names(logging.Handler):
    def emit(self, record):
        text = record.getMessage()
        if text.startswith("Compiling "):
            names.append(text.split()[1].removeprefix("jit(").rstrip(")"))
logging.getLogger("jax").addHandler(Names())
jax.config.update("jax_log_compiles", True)
import jaxtrack as jt, trimesh
from jaxtrack.render import make_mesh
from jaxtrack.track import Tracker, TrackerConfig
box = trimesh.creation.box((70.0, 50.0, 30.0))
K = np.array([[90.0, 0, 38], [0, 90.0, 27], [0, 0, 1]])
from jaxtrack.geometry import make_camera, stack_cameras
rig = stack_cameras([make_camera(K, 76, 54), make_camera(K, 76, 54, t_cam_world=[5.0, 0, 0])])
tracker = Tracker(make_mesh(box.vertices, box.faces), rig, config=TrackerConfig(cues=("region",)))
frames = np.random.default_rng(0).integers(0, 255, (2, 54, 76, 3), np.uint8)
T = np.eye(4); T[2, 3] = 350.0
tracker.start(frames, T)
print("NAMES", " ".join(names))
"""


def test_building_a_rig_a_mesh_and_starting_a_tracker_runs_no_eager_programs():
    """Host values go to the device with `to_device` (`jax.device_put`), not `jnp.asarray`, and host planning runs in
    numpy: in a fresh process each eager jnp operation (a copy "stage", a cast, a slice of a device array) compiles
    a program of its own, 10-30 ms each; about 70 of them made a warm tracker start ~0.4 s slower. Only the tracker's
    own programs compile here."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", _EAGER_SCRIPT], check=False, capture_output=True, text=True, env=env,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = next(line.split()[1:] for line in proc.stdout.splitlines() if line.startswith("NAMES"))
    assert names  # the tracker's programs are seen compiling
    eager = [n for n in names if n == "stage" or hasattr(jnp, n) or hasattr(jax.lax, n)]
    assert not eager, eager


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_default_params_are_strongly_typed_so_the_step_is_kept(dtype):
    """`persistent_jit` sends weakly typed arguments to the plain path (a kept program takes strongly typed ones): a
    weak leaf in the tracker's parameters would make every process trace and compile its step again."""
    from jaxtrack._device import to_device
    from jaxtrack.geometry import rigid_model
    from jaxtrack.track import default_params

    params = default_params(rigid_model(dtype), (48, 64), dtype)
    weak = [path for path, x in jax.tree_util.tree_leaves_with_path(params) if getattr(x, "weak_type", False)]
    assert not weak, weak
    assert {x.dtype for x in jax.tree.leaves(params) if jnp.issubdtype(x.dtype, jnp.floating)} == {jnp.dtype(dtype)}
    assert to_device(1.0).weak_type and not to_device(to_device(1.0), dtype).weak_type


def test_the_programs_compile_with_the_cpu_compiler_options(folder, monkeypatch):
    """Both paths (kept and plain) pass `compiler_options()` to XLA: an option XLA does not know makes them fail, the
    fast-compile options give eqx.filter_jit's outputs; XLA's defaults without $JAXTRACK_FUSION_EMITTERS (or = 1) and
    on other backends, and a bad value names the variable."""
    monkeypatch.delenv("JAXTRACK_FUSION_EMITTERS", raising=False)
    assert _exported.compiler_options("cpu") is None
    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "1")
    assert _exported.compiler_options("cpu") is None
    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "yes")
    with pytest.raises(ValueError, match="JAXTRACK_FUSION_EMITTERS"):
        _exported.compiler_options("cpu")
    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "0")
    assert _exported.compiler_options("cpu") == {"xla_cpu_use_fusion_emitters": False}
    assert _exported.compiler_options("gpu") is None
    m, x = Scaled(jnp.arange(3.0), 2), jnp.array([1.0, -2.0, 0.5])
    expected = eqx.filter_jit(model)(m, x)
    kept, plain = persistent_jit(model), persistent_jit(model)
    monkeypatch.setattr(_exported, "_FOLDER", [None])
    assert np.array_equal(np.asarray(plain(m, x)[1]), np.asarray(expected[1]))
    monkeypatch.setattr(_exported, "_FOLDER", [folder])
    assert np.array_equal(np.asarray(kept(m, x)[1]), np.asarray(expected[1])) and kept.exported == 1
    monkeypatch.setattr(_exported, "CPU_COMPILER_OPTIONS", {"xla_cpu_no_such_option": True})
    with pytest.warns(RuntimeWarning, match="kept program"), pytest.raises(Exception, match="xla_cpu_no_such_option"):
        persistent_jit(model)(m, 2 * x)  # kept: its program fails, then the plain path reports it
    monkeypatch.setattr(_exported, "_FOLDER", [None])
    with pytest.raises(Exception, match="xla_cpu_no_such_option"):
        plain(m, 3 * x)  # a new options set: compiled again with them
    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "1")
    assert np.array_equal(np.asarray(plain(m, 3 * x)[1]), np.asarray(eqx.filter_jit(model)(m, 3 * x)[1]))


def test_a_call_inside_a_callers_jit_with_concrete_arguments_runs_in_the_callers_program(folder, monkeypatch):
    """XLA takes compile options only for a top-level program: a kept or plain call traced inside a caller's jit whose
    arguments are all concrete (no tracer tells) runs without them, warns nothing and keeps its entry for later
    top-level calls."""
    import warnings

    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "0")
    m, x = Scaled(jnp.arange(3.0), 2), jnp.array([1.0, -2.0, 0.5])
    expected = float(eqx.filter_jit(model)(m, x)[1])
    for kept in (True, False):
        monkeypatch.setattr(_exported, "_FOLDER", [folder if kept else None])
        f = persistent_jit(model)
        assert float(f(m, x)[1]) == expected  # top level first: the entry (or plain program) with the options
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            inside = jax.jit(lambda f=f: f(m, x)[1])()  # m and x closed over: concrete inside the caller's trace
        assert float(inside) == pytest.approx(expected)
        if kept:
            assert all(entry is not _exported._PLAIN for entry in f.memory.values()) and len(f.memory) == 1
        assert float(f(m, 2 * x)[1]) == pytest.approx(float(eqx.filter_jit(model)(m, 2 * x)[1]))


TIERED_SCRIPT = r"""
import json, os, pathlib, sys
import jax, jax.numpy as jnp, numpy as np
import jax.monitoring
from jaxtrack import enable_compilation_cache
from jaxtrack import _tiered
from jaxtrack._exported import persistent_jit
from jaxtrack.geometry import se3_exp

events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name.rsplit("/", 1)[-1]) if "compilation_cache" in name else None)
enable_compilation_cache(sys.argv[1])
xi = jnp.array([0.1, -0.2, 0.3, 10.0, 20.0, 30.0], jnp.float32)
out = {}
f = persistent_jit(se3_exp, tiered=True)
first = f(xi)
out["first_options"] = [dict(k[-1]) for k in f.memory]
out["requested"] = _tiered.optimise_counts()[0]
n = len(events)
out["waited"] = _tiered.wait_for_optimised_programs(timeout=120)
out["wait_events"] = events[n:]
out["failures"] = _tiered.optimise_failures()
out["swapped"] = _tiered.optimise_counts()[1]
second = f(xi)
out["options_after"] = sorted(json.dumps(dict(k[-1])) for k in f.memory)
out["max_diff"] = float(np.max(np.abs(np.asarray(first) - np.asarray(second))))
out["marks"] = sorted(p.name.split(".", 1)[1] for p in pathlib.Path(sys.argv[1], "exported").iterdir())
fresh = persistent_jit(se3_exp, tiered=True)  # a later process: nothing in memory, the mark on disk
fresh(xi)
out["fresh_options"] = [dict(k[-1]) for k in fresh.memory]
out["requested_after_fresh"] = _tiered.optimise_counts()[0]
print("RESULT " + json.dumps(out))
"""


def test_a_tiered_program_runs_its_quick_build_first_then_the_optimised_one_a_child_process_compiled(tmp_path):
    """`persistent_jit(..., tiered=True)` in the default mode ($JAXTRACK_FUSION_EMITTERS unset) with an empty cache: the
    first call compiles with the quick options; a child process compiles XLA's default build into the compile cache and
    marks it; this process loads it (a hit in the compile cache, not a compile) and runs it from then on (the same
    values); a later wrapper (a new process) that finds the mark runs the optimised build at once and asks for nothing."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAXTRACK_FUSION_EMITTERS", "JAXTRACK_EXPORT_CACHE")}
    proc = subprocess.run([sys.executable, "-c", TIERED_SCRIPT, str(tmp_path / "cache")], capture_output=True, text=True,
                          env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = __import__("json").loads(next(line for line in proc.stdout.splitlines() if line.startswith("RESULT "))[7:])
    quick = dict(_exported.CPU_COMPILER_OPTIONS)
    assert out["first_options"] == [quick] and out["requested"] == 1
    assert out["waited"] and out["failures"] == [] and out["swapped"] == 1
    assert "cache_hits" in out["wait_events"] and "cache_misses" not in out["wait_events"], out["wait_events"]
    assert out["options_after"] == sorted(['{}', __import__("json").dumps(quick)])
    assert out["max_diff"] < 1e-4
    assert out["marks"] == ["jaxexport", "jaxexport.optimised"]
    assert out["fresh_options"] == [{}] and out["requested_after_fresh"] == 1


def test_the_fusion_emitters_setting_names_its_modes(monkeypatch):
    """$JAXTRACK_FUSION_EMITTERS: unset or auto → tiered on the CPU, 0 → quick, 1 → XLA's defaults; any backend but the
    CPU compiles once with XLA's defaults; another value names the variable."""
    monkeypatch.delenv("JAXTRACK_FUSION_EMITTERS", raising=False)
    assert _exported.compile_mode("cpu") == "tiered" and _exported.compile_mode("gpu") == "default"
    for value, mode in (("auto", "tiered"), ("0", "quick"), ("1", "default")):
        monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", value)
        assert _exported.compile_mode("cpu") == mode
    monkeypatch.setenv("JAXTRACK_FUSION_EMITTERS", "tiered")
    with pytest.raises(ValueError, match="JAXTRACK_FUSION_EMITTERS must be 0, 1 or auto"):
        _exported.compile_mode("cpu")


def test_is_kept_says_whether_a_signature_is_on_disk_without_loading_it(folder, monkeypatch):
    """`persistent_jit.is_kept`: False before the program is exported, True after (for another wrapper too: a later
    process), False for another shape, under no folder and for weakly typed arrays (the calls that run
    eqx.filter_jit)."""
    m, x = Scaled(jnp.arange(3.0), 2), jnp.array([1.0, -2.0, 0.5])
    f = persistent_jit(model)
    assert not f.is_kept(m, x)
    f(m, x)
    fresh = persistent_jit(model)
    assert fresh.is_kept(m, x) and not fresh.memory and fresh.loaded == 0  # nothing loaded
    assert not fresh.is_kept(m, jnp.ones(4))
    assert not fresh.is_kept(Scaled(jnp.arange(3.0), 2), 1.0 * jnp.asarray(2.0))  # a weakly typed scalar
    monkeypatch.setattr(_exported, "_FOLDER", [None])
    assert not fresh.is_kept(m, x)


def test_a_failed_optimising_child_is_reported_and_releases_its_locks(tmp_path):
    """A child that cannot compile its program (the file is gone) exits 1 with the reason, leaves no mark and releases
    the lock it held; a lock whose holder process is gone is taken over, one a live process holds is not."""
    from jaxtrack import _tiered

    program = tmp_path / "gone.jaxexport"
    assert _tiered._take_lock(program) and not _tiered._take_lock(program)  # held by this (live) process
    failures = []
    request = _tiered.Request(program=program, avals=(((3,), "float32"),), make_entry=None, swap=None, structs=())
    _tiered._run_child([request], failures)
    assert len(failures) == 1 and "gone.jaxexport" in failures[0] and "FileNotFoundError" in failures[0], failures
    assert not _tiered.lock_path(program).exists() and not _tiered.is_marked(program)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    _tiered.lock_path(program).write_text(dead.stdout.strip())  # a lock of a process that has exited
    assert not _tiered._lock_held(program) and _tiered._take_lock(program)
    _tiered._release(program, os.getpid())
    assert not _tiered.lock_path(program).exists()


def test_the_optimised_text_of_a_kept_program_that_ran_names_its_source_lines(folder):
    """`optimised_hlo_texts`: XLA's optimised HLO of each kept program that has run, with the stack frames that
    `jaxtrack.bench.profile_kernels` maps its kernels through."""
    from jaxtrack.bench import instruction_frames

    m, x = Scaled(jnp.arange(3.0), 2), jnp.array([1.0, -2.0, 0.5])
    program = persistent_jit(model)
    jax.block_until_ready(program(m, x, factor=3.0)[1])
    texts = _exported.optimised_hlo_texts()
    assert texts and all(t.startswith("HloModule") for t in texts)
    line = model.__code__.co_firstlineno + 3  # y = factor * (m.weights * x) ** m.power
    frames = [f for t in texts for stack in instruction_frames(t).values() for f in stack]
    assert any(f.function == "model" and f.line == line and f.file.endswith("test_exported.py") for f in frames)
