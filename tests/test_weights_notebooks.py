"""Smoke runs of experiments 7 (vmap cue-weight sweep) and 8 (learned cue weights) and of the notebooks
(quickstart, gradients, weight_sweep), on the `tracker_quick` configuration (occluded box 96x72, region
cue, 4 frames) so that one worker compiles each program once: the single step (shared with
tests/test_experiments.py), the vmapped step over 4 settings (the sweep, the learning script's
evaluation and the weight-sweep notebook) and the forward-mode step (the learning script and the
gradients notebook). The notebooks' code cells run in this process with their smoke sizes.
"""

import importlib
import os
import pathlib
import sys

import equinox as eqx
import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXPERIMENTS = ROOT / "experiments"
NOTEBOOKS = ROOT / "notebooks"


def _experiment(name):
    """The experiment module imported by name (learn_weights and the notebooks import weight_sweep the same
    way: one module, so one jitted vmapped step whose compiled program they share)."""
    if str(EXPERIMENTS) not in sys.path:
        sys.path.insert(0, str(EXPERIMENTS))
    return importlib.import_module(name)


def _traces():
    from jaxtrack.track import track_step

    return eqx.debug.get_num_traces(track_step)


def _table(text, header_start):
    """Rows (cells) of the markdown table whose header starts with `header_start`."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def _run_notebook(builder: str) -> dict:
    """Execute the code cells of notebooks/`builder`.py in this process with the smoke sizes; the namespace."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = importlib.util.spec_from_file_location(builder, NOTEBOOKS / f"{builder}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    old = {k: os.environ.get(k) for k in ("JAXTRACK_NOTEBOOK_SMOKE", "JAXTRACK_ROOT")}
    os.environ.update(JAXTRACK_NOTEBOOK_SMOKE="1", JAXTRACK_ROOT=str(ROOT))
    namespace: dict = {}
    try:
        for kind, source in module.CELLS:
            if kind == "code":
                exec(compile(source, f"{builder}.ipynb", "exec"), namespace)  # noqa: S102 - the notebook's own cells
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        plt.close("all")
    return namespace


@pytest.fixture(scope="module")
def sweep_quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("weight_sweep") / "w.md"
    before = _traces()
    result = _experiment("weight_sweep").main(["--quick", "--out", str(out)])
    return result, out.read_text(), _traces() - before


@pytest.fixture(scope="module")
def learn_quick(sweep_quick, tmp_path_factory):
    out = tmp_path_factory.mktemp("learn_weights") / "l.md"
    before = _traces()
    result = _experiment("learn_weights").main(["--quick", "--out", str(out)])
    return result, out.read_text(), _traces() - before


@pytest.mark.xdist_group("tracker_quick")
def test_weight_sweep_quick(sweep_quick):
    result, text, traced = sweep_quick
    assert traced == 1  # one vmapped program for the 4 settings, traced once for all frames
    run = result["run"]
    assert run["rot_deg"].shape == (4, 4) and np.all(np.isfinite(run["rot_deg"]))
    assert len(run["step_s"]) == 3 and run["traced"] == [True, False, False]
    # RBOT resets: a setting restarts exactly where it failed.
    np.testing.assert_array_equal(run["reset"][:, 1:], ~run["success"][:, 1:])
    # Region cue only: the flow and SIFT factors have no rows to weigh, so every setting tracks alike.
    flat = [c for row in result["scores"] for c in row]
    assert all(c["rot_deg"] == flat[0]["rot_deg"] and c["success"] == flat[0]["success"] for c in flat)
    rows = _table(text, "| SIFT \\ flow |")
    assert [r[0] for r in rows] == ["1", "10"] and all(len(r) == 3 for r in rows)
    assert "(D" in rows[0][1] and "(P" in rows[0][2]  # the tracker's default and the paper's weights are marked
    every = _table(text, "| flow | SIFT |")
    assert len(every) == 4 and all(r[2].endswith("%") for r in every)


@pytest.mark.xdist_group("tracker_quick")
def test_learn_weights_quick(learn_quick):
    """The forward-mode step compiles once (the smallest case; its compile is most of this test's time) and
    the evaluation reuses the sweep's vmapped program; with the region cue alone the flow and SIFT factors
    weigh nothing, so forward mode and finite differences both give exactly zero."""
    result, text, traced = learn_quick
    assert traced == 1  # the forward-mode step; the 4-setting evaluation reused weight_sweep's program
    check = result["check"]
    assert check["jvp"] == [0.0, 0.0] and check["fd"] == [[0.0, 0.0]]
    assert np.isfinite(check["loss"]) and check["loss"] > 0
    hist = result["history"]
    assert len(hist) == 2 and hist[0]["flow"] == pytest.approx(0.1) and hist[0]["sift"] == pytest.approx(1.0)
    ev = next(iter(result["evals"].values()))
    assert list(ev) == ["paper (1, 1)", "default (0.1, 1)", "learned", "learned flow, SIFT 1"]
    assert len({round(r[2]["rot_deg"], 9) for r in ev.values()}) == 1
    assert len(_table(text, "| parameter |")) == 2 and len(_table(text, "| sequence |")) == 4
    assert "Reverse mode" in text and "forward mode" in text


@pytest.mark.xdist_group("tracker_quick")
def test_gradients_notebook_smoke(learn_quick):
    before = _traces()
    ns = _run_notebook("build_gradients_notebook")
    assert _traces() == before  # the forward-mode step compiled by the learning script is reused
    # float64 energies and the implicit derivative of the solve agree with central differences.
    assert ns["flow_rel"] < 1e-6 and ns["levelset_rel"] < 1e-6 and ns["pose_rel"] < 1e-5
    np.testing.assert_array_equal(ns["tracking_grad"], [0.0, 0.0])


@pytest.mark.xdist_group("tracker_quick")
def test_weight_sweep_notebook_smoke(sweep_quick):
    before = _traces()
    ns = _run_notebook("build_weight_sweep_notebook")
    assert _traces() == before  # the vmapped program of weight_sweep --quick is reused
    assert ns["small"].shape == (2, 2) and np.all(np.isfinite(ns["small"]))
    np.testing.assert_allclose(ns["small"].ravel(), [c["rot_deg"] for row in sweep_quick[0]["scores"] for c in row])


@pytest.mark.xdist_group("tracker_quick")
def test_quickstart_notebook_smoke():
    ns = _run_notebook("build_quickstart_notebook")
    run = ns["run"]
    assert len(run.status) == 4 and np.all(np.isfinite(ns["rot"])) and ns["rot"][0] < 0.1  # frame 0: the true pose (float32)
    assert len(ns["records"]) == 4 and ns["records"][1].region_phi is not None
