"""Smoke versions of the benchmarks in experiments/ (the full runs write experiments/results/)."""

import importlib.util
import pathlib

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1] / "experiments"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_pose_quick(tmp_path):
    rows, throughput = _load("bench_pose").main(["--quick", "--trials", "4", "--out", str(tmp_path / "t.md")])
    text = (tmp_path / "t.md").read_text()
    assert "| jaxtrack |" in text and "SOLVEPNP_SQPNP" in text
    ours = [r for r in rows if r[2] == "jaxtrack"]
    # Same cost as SQPNP (object-space error): the errors match within a few percent.
    assert all(0.9 < r[7] < 1.1 and 0.9 < r[8] < 1.1 for r in ours), ours
    assert throughput[0][4] == 1.0  # every batched solve converged
