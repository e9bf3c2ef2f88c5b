"""Shared fixtures. Tests run in float64 (gradient checks against finite differences need it);
float32 paths are exercised explicitly where they matter."""

import os
import pathlib

import jax
import pytest

jax.config.update("jax_enable_x64", True)

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
