"""Shared fixtures. Tests run in float64 (gradient checks against finite differences need it);
float32 paths are exercised explicitly where they matter."""

import os
import pathlib
import shutil
import tempfile

# Compile at LLVM's lowest optimisation level. Compilation dominates this suite (small images, few
# iterations), and O0 roughly halves it: test_vmap_over_cue_weights_equals_separate_runs with its fixture
# 134 s → 85 s alone. The programs run slower, which the suite's few-frame runs barely notice; the product
# keeps XLA's default. Set here, before JAX starts its backend; the xdist workers import this file too.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

import jax
import pytest

# The correspondence-line modality builds a sparse view model per new mesh (2562 views: about 30 s each on
# 2 cores, cached in ~/.cache/jaxtrack/viewmodels); the suite's trackers use 162 views (same code path).
os.environ.setdefault("JAXTRACK_VIEW_SUBDIVISIONS", "2")
# Trackers (recovery is on by default) compile their recovery program in the tracking thread when a frame is first
# lost, not in the background at the first doubt, where whether a lost frame searched would depend on the timing
# (tests/test_tracker.py checks the warm-up itself).
os.environ.setdefault("JAXTRACK_RECOVERY_WARMUP", "0")
# No exported programs on disk (`jaxtrack._exported`) even where a test runs `jaxtrack track` in this process: the
# exported step compiles as another XLA program than the plain one the other tests share, and a program loaded from
# disk is not traced, which the trace-count tests would read as a missing trace. tests/test_exported.py turns it on.
os.environ.setdefault("JAXTRACK_EXPORT_CACHE", "0")
# The tracker's programs with XLA:CPU's older emitters ($JAXTRACK_FUSION_EMITTERS=0, `jaxtrack._exported`): XLA compiles
# them in about two thirds of the time and they run 15-30 % slower, and the suite's trackers run a few frames each. The
# product compiles its step in two tiers, this build first and XLA's default from a background process (`jaxtrack._tiered`;
# tests/test_exported.py checks the split step's equality with the default and the tiers in a subprocess).
os.environ.setdefault("JAXTRACK_FUSION_EMITTERS", "0")
# The suite checks the tracker's defaults: the opt-in motion rounds of an experiment's shell are not inherited.
os.environ.pop("JAXTRACK_MOTION_ROUNDS", None)
os.environ.pop("JAXTRACK_MOTION_LATE_FACTOR", None)

jax.config.update("jax_enable_x64", True)


_CACHE_ENV = "JAXTRACK_TEST_XLA_CACHE"
_cache_owner = pytest.StashKey[str]()


def pytest_configure(config):
    """One XLA compilation cache per test run, shared by its xdist workers: the controller makes the folder
    before it starts the workers, which inherit its environment. Compilation dominates the suite, and many
    programs (the pose solver, flow at the shared test sizes, renders) are needed by tests on both
    workers: one compiles, the other loads. The controller removes the folder at the end."""
    if not hasattr(config, "workerinput") and _CACHE_ENV not in os.environ:
        os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxtrack-tests-xla-")
        config.stash[_cache_owner] = os.environ[_CACHE_ENV]
    jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_ENV])
    # Every program goes to the shared cache, not only those that took over a second to compile (jax's default; the
    # product's `jaxtrack.enable_compilation_cache` does the same): the suite compiles many small programs,
    # some needed on both workers, or again in a worker after `_bounded_mappings` cleared its caches. Measured with
    # `-n 2` on 2026-12-02, the two settings alternated: the solver, Lie, geometry, image and flow-energy tests 400 →
    # 341 s, the flow-solver, SIFT and render tests 267 → 243 s (this setting run first there).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    os.environ["JAXTRACK_CACHE_DIR"] = os.environ[_CACHE_ENV]  # where `jaxtrack track` without --no-cache writes
    # The meshes' geometry cache (`jaxtrack.io.mesh_cache_dir`) in the run's folder too, not the user's ~/.cache.
    os.environ.setdefault("JAXTRACK_MESH_CACHE", os.path.join(os.environ[_CACHE_ENV], "meshes"))


def pytest_unconfigure(config):
    folder = config.stash.get(_cache_owner, None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(_CACHE_ENV, None)


# Each compiled XLA:CPU program maps about three memory regions, and a worker that runs half the suite compiles
# thousands of programs: measured, a worker reached 64 896 mappings and died with a segfault at Linux's default
# vm.max_map_count of 65 530 (the run then hung). Past this many mappings a test's end clears jax's caches, which
# unmaps the programs (the on-disk compilation cache gives them back to the tests that need them again).
MAX_MAPPINGS = 40_000


def _mappings() -> int:
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux: no such limit to watch
        return 0


@pytest.fixture(autouse=True)
def _bounded_mappings():
    yield
    if _mappings() > MAX_MAPPINGS:
        import gc

        jax.clear_caches()
        gc.collect()


SHARED_DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> pathlib.Path:
    """../shared/data; skips when absent, fails when JAXTRACK_REQUIRE_SHARED=1 (CI)."""
    if not SHARED_DATA.is_dir():
        if os.environ.get("JAXTRACK_REQUIRE_SHARED") == "1":
            pytest.fail(f"JAXTRACK_REQUIRE_SHARED=1 but {SHARED_DATA} is missing")
        pytest.skip(f"{SHARED_DATA} not found")
    return SHARED_DATA


def pytest_collection_modifyitems(config, items):
    """Tests marked `heavy` (long, no shared module fixture) run first: under `-n 2` each worker then starts
    with one of them instead of one worker finishing a four-minute test alone at the end."""
    items.sort(key=lambda item: item.get_closest_marker("heavy") is None)

