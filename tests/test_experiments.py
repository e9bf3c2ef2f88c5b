"""Smoke versions of the benchmarks in experiments/ (the full runs write experiments/results/)."""

import importlib.util
import pathlib
import sys

import numpy as np
import pytest

EXPERIMENTS = pathlib.Path(__file__).resolve().parents[1] / "experiments"


def _load(name):
    """experiments/NAME.py as a module. Its folder goes first on sys.path (once), as it does for
    `python experiments/NAME.py`: the scripts import their siblings (track_presets, noise_table, ...)."""
    if str(EXPERIMENTS) not in sys.path:
        sys.path.insert(0, str(EXPERIMENTS))
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


def test_init_points_quick(tmp_path):
    """experiments/init_points.py: pose_from_points against the truth; both outliers found in every 10-point scene."""
    text = _load("init_points").main(["--trials", "4", "--out", str(tmp_path / "p.md")])
    assert (tmp_path / "p.md").read_text() == text
    rows = {line.split(" | ")[0].strip("| "): line for line in text.splitlines()
            if line.startswith(("| 4 points", "| 10 points"))}
    assert set(rows) == {"4 points: EPnP alone", "4 points: SQPnP alone", "4 points: pose_from_points",
                         "10 points, 2 outliers: pose_from_points"}
    assert "both, exactly, in 4 of 4" in rows["10 points, 2 outliers: pose_from_points"]
    worst = float(rows["10 points, 2 outliers: pose_from_points"].split(" | ")[1].split(" / ")[1])
    assert worst < 5.0


@pytest.mark.heavy
def test_bench_flow_quick(tmp_path, shared_data):
    out = tmp_path / "flow.md"
    # The pyramid's levels from 1 on as one compiled level (the same flow to rounding: tests/test_flow_solver.py), which
    # compiles faster than the benchmark's unrolled pyramid (first calls 22 / 20 → 18 / 12 s on 2026-12-02's machine).
    _load("bench_flow").main(["--quick", "--out", str(out), "--viz", str(tmp_path / "flow.png"), "--shared-levels-from", "1"])
    text = out.read_text()
    rows = {line.split("|")[1].strip(): line.split("|") for line in text.splitlines() if line.startswith("| ")}
    rw = rows["RubberWhale"]
    epe_ours, epe_dis, epe_fb = float(rw[3]), float(rw[6]), float(rw[9])
    # The variational solution beats both OpenCV baselines on this pair (measured ~0.14 vs ~0.3-0.4).
    assert epe_ours < 0.25 and epe_ours < epe_dis and epe_ours < epe_fb
    assert float(rows["Yosemite (terrain)"][4]) < 6.0  # AAE in degrees (measured 4.3 at the Middlebury setting)
    assert (tmp_path / "flow.png").stat().st_size > 1000
    assert "pyramid levels from 1 on one compiled level" in text


# --- tracker speed and preset success (issue 11): one compiled program shared by both smoke runs -------------------
def _markdown_rows(text, first_cell):
    """Cells of the markdown table rows whose first cell is `first_cell`."""
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| ") and line.strip("| ").split("|")[0].strip() == first_cell]


@pytest.fixture(scope="module")
def track_smoke(tmp_path_factory):
    """bench_track --quick, then track_presets --quick on the same 96x72 frames and configuration (the
    second run reuses the first one's compiled step); M3T columns when the baseline is built."""
    out = tmp_path_factory.mktemp("track_smoke")
    bench = _load("bench_track")
    bench_rows, bench_m3t = bench.main(["--quick", "--out", str(out / "bench.md")])
    preset_rows = _load("track_presets").main(["--quick", "--out", str(out / "presets.md")])
    return {"bench": (bench_rows, bench_m3t, (out / "bench.md").read_text()),
            "presets": (preset_rows, (out / "presets.md").read_text()), "m3t": bench.m3t_available()}


@pytest.mark.xdist_group("tracker_quick")
def test_bench_track_quick(track_smoke):
    rows, _, text = track_smoke["bench"]
    cold, warm = rows[("region", 1)]
    assert warm is None  # --quick runs in-process: no warm-cache run
    assert np.isfinite(cold["frame_ms"]) and cold["frame_ms"] > 0 and cold["timed"] >= 1
    assert 0 < cold["start_s"] < cold["ready_s"] and cold["first_step_s"] > 0
    stages = cold["stages"]
    # Stages timed through the modality protocol: the region modality's rows per round, its update, the solves.
    region = next(k.split(":")[0] for k in stages["ms"] if k.endswith(": rows"))
    assert region in ("lines", "levelset")
    for name in ("frame context (crops, render at t)", "render", f"{region}: start", f"{region}: rows",
                 f"{region}: update", "refinement solve"):
        assert np.isfinite(stages["ms"][name]) and stages["ms"][name] >= 0, name
    assert stages["calls"][f"{region}: rows"] == stages["calls"]["refinement solve"] == stages["rounds"] >= 1
    # The table: one row for the configuration with every column filled, the breakdown and the goals.
    row = _markdown_rows(text, "region")[0]
    assert len(row) == 14 and row[1] == "1" and float(row[3]) > 0
    assert row[11] == "- (one build)"  # the suite's quick build only ($JAXTRACK_FUSION_EMITTERS=0): no second tier
    assert "| sum of the stages |" in text and "| whole step (`Tracker.step`, same inputs) |" in text
    assert "region only, 1 camera:" in text and "ms per frame (goal ≤ 10)" in text


@pytest.mark.xdist_group("tracker_quick")
def test_bench_track_quick_m3t(track_smoke):
    smoke = track_smoke
    if not smoke["m3t"]:
        pytest.skip("M3T baseline not built (~/.cache/m3t-baseline/build/m3t_run_bop): M3T columns not checked")
    _, m3t, text = smoke["bench"]
    assert set(m3t) == {"region", "regtex"} and all(0 < r["ms"] < 1000 and r["frames"] == 3 for r in m3t.values())
    assert _markdown_rows(text, "regtex")


@pytest.mark.xdist_group("tracker_quick")
def test_track_presets_quick(track_smoke):
    rows, text = track_smoke["presets"]
    ours = [r for r in rows if r[0] == "jaxtrack"]
    assert [(r[1], r[2]) for r in ours] == [("region", "occluded-box")]
    r = ours[0][3]
    assert r["frames"] == 3 and r["cameras"] == 1 and 0 <= r["success"] <= 1
    assert r["failures"] == round((1 - r["success"]) * r["frames"])
    assert np.isfinite(r["rot_deg"]) and np.isfinite(r["trans_mm"])
    # Success table: a row per method with one cell per preset; the detail table names the preset.
    cells = _markdown_rows(text, "jaxtrack")[0]
    assert cells[1] == "region" and cells[2].endswith("%")
    detail = _markdown_rows(text, "occluded-box")
    assert detail and detail[0][1] == "jaxtrack" and detail[0][4] == "3"


@pytest.mark.xdist_group("tracker_quick")
def test_track_presets_quick_m3t(track_smoke):
    smoke = track_smoke
    if not smoke["m3t"]:
        pytest.skip("M3T baseline not built (~/.cache/m3t-baseline/build/m3t_run_bop): M3T columns not checked")
    rows, text = smoke["presets"]
    m3t = {r[1]: r[3] for r in rows if r[0] == "M3T"}
    assert set(m3t) == {"region", "regtex"}
    assert all(r["frames"] == 3 and 0 <= r["success"] <= 1 and np.isfinite(r["rot_deg"]) for r in m3t.values())
    assert len(_markdown_rows(text, "M3T")) == 2


def test_loss_detection_calibration_and_report():
    """The calibration of experiments/loss_detection.py without tracking: the logistic fit recovers known weights
    from frames drawn under them, the two models (the frame's evidence alone, and with the running averages) take
    the tracker's layout, and the report scores the tracker's statuses and the refit against the truth; the
    re-analysis (--analyse) recomputes the averages for each decay as the tracker does and cross-validates them."""
    from jaxtrack._status import Status

    ld = _load("loss_detection")
    rng = np.random.default_rng(0)
    n = len(ld.FEATURES)
    scale = np.resize([0.5, 1, 0.5, 0.5, 2], n)
    w_true = np.array([-4.0, 3.0, 1.0, 4.0, 2.0, 0.5, 2.0, 1.0, 2.0, 1.0, 0.5])  # intercept, frame, averages
    rows = []
    for _ in range(20000):
        features = dict(zip(ld.FEATURES, rng.uniform(0, 1, n) * scale, strict=True))
        p = 1 / (1 + np.exp(-(w_true[0] + np.dot(w_true[1:], list(features.values())))))
        failed = bool(rng.random() < p)
        rows.append({**features, "failed": failed, "rot_deg": 10.0 if failed else 1.0, "trans_mm": 1.0,
                     "confidence": 1 - p, "status": int(Status.LOST if p > 0.75 else Status.UNCERTAIN if p > 0.5 else Status.OK)})
    w = ld.fit_logistic(ld.design(rows), np.array([r["failed"] for r in rows], float), l2=0.0)
    np.testing.assert_allclose(w, w_true, atol=0.5)  # 20000 Bernoulli draws: standard errors 0.05-0.3
    models = ld.fit_models(rows[:10000])
    frame_columns = 1 + len(ld.LOSS_FRAME_EVIDENCE)
    assert models.shape == (2, n + 1) and not np.any(models[0, frame_columns:]) and np.all(models[1, frame_columns:] != 0)
    text = ld.report("cmd", 1.0, ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), [("c", rows[:10000])], [("e", rows[10000:])], models)
    line = next(t for t in text.splitlines() if t.startswith("| **all** |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    flagged = sum(r["status"] != int(Status.OK) for r in rows[10000:])
    assert int(cells[3]) == flagged and all(0.0 <= float(c) <= 1.0 for c in cells[4:])

    few = [dict(rows[i], **{f: float(i + 1) for f in ld.LOSS_FRAME_EVIDENCE}) for i in range(3)]
    averaged = ld.with_averages([("s", few)], 0.5)[0][1]
    assert [r[f"{ld.LOSS_FRAME_EVIDENCE[0]}_avg"] for r in averaged] == [0.5, 1.25, 2.125]  # from zeros: a·avg + (1−a)·frame
    saved = {"features": list(ld.FEATURES), "calibration": [(f"c{i}", rows[500 * i:500 * (i + 1)]) for i in range(12)],
             "evaluation": [("e", rows[10000:11000])]}
    analysis = ld.analyse(saved, "cmd")
    table = [t for t in analysis.splitlines() if t.startswith(("| the frame alone", "| with the averages"))]
    assert len(table) == 1 + len(ld.DECAYS)
    assert all(0.0 < float(t.split("|")[2]) < 1.0 for t in table)  # cross-validated log-losses


def test_recovery_report_compares_the_modes():
    """experiments/recovery.py's report without tracking: success rates per mode, their mean, the failure runs and the
    recovery run's counts come from the rows it is given."""
    rec = _load("recovery")

    def rows(failed, status=None, searched=()):
        out = []
        for k, f in enumerate(failed):
            s = (status or ["OK"] * len(failed))[k]
            out.append({"failed": f, "status": s, "searched": k in searched, "recovered": s == "RECOVERED",
                        "source": "keyframes" if k in searched else None, "total_s": 0.05,
                        "recovery_s": 0.2 if k in searched else None})
        return out

    runs = {"a": {"no recovery": rows([False, True, True, True]),
                  "recovery": rows([False, True, False, False], ["OK", "LOST", "RECOVERED", "OK"], searched=(1, 2)),
                  "RBOT resets": rows([False, True, False, False])},
            "b": {m: rows([False, False]) for m in rec.MODES}}
    text = rec.report("cmd", 60.0, ((0.0,) * 3, (0.0,) * 3), runs)
    row = next(t for t in text.splitlines() if t.startswith("| a |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:6] == ["25 %", "75 %", "75 %", "+0"] and cells[6] == "3(end)" and cells[7] == "1"
    mean = next(t for t in text.splitlines() if t.startswith("| **mean"))
    assert "**62.5 %**" in mean and "**87.5 %**" in mean
    assert "RECOVERED: 1, of which within the bound: 1; found by the keyframes' PnP: 1" in text


def test_flow_compile_quick(tmp_path):
    """experiments/flow_compile.py: the shared coarse levels give the unrolled flow and the motion is found."""
    results = _load("flow_compile").main(["--quick", "--out", str(tmp_path / "f.md")])
    (_, _, levels, rows), = results
    assert levels >= 3 and [r["k"] for r in rows] == [0, 1]
    assert rows[1]["max_diff"] < 1e-3 and all(r["epe"] < 0.5 for r in rows), rows
    assert "| smoke | 32x48 |" in (tmp_path / "f.md").read_text()


def test_first_frame_compile_quick(tmp_path):
    """experiments/first_frame_compile.py: a fresh process tracks a frame and the compile log is read."""
    runs = _load("first_frame_compile").main(["--quick", "--out", str(tmp_path / "c.md")])
    (row,) = runs["lines"]
    assert row["xla_s"] > 0 and row["first_frame_s"] >= row["start_s"] > 0 and row["largest_xla_s"]
    assert "| region | 1 |" in (tmp_path / "c.md").read_text()


def test_human_table2_checks_its_working_shape_and_region_options():
    """experiments/human_table2.py: `--working-shape HxW` is parsed once, before any sequence is rendered; a malformed
    one and an unknown `--region` stop with a message naming the option."""
    module = _load("human_table2")
    assert module._shape("128x96") == (128, 96) and module._shape(None) is None
    with pytest.raises(SystemExit, match="--working-shape must be HxW"):
        module.main(["--working-shape", "128", "--out", ""])
    with pytest.raises(SystemExit):
        module.main(["--region", "dense", "--out", ""])


def test_energy_bias_summary_and_report():
    """experiments/energy_bias.py without tracking: the summary's means, maxima, signed depth and the frames beyond
    5° / 50 mm come from the rows, and the report has one row per (sequence, cue set) with them."""
    eb = _load("energy_bias")
    rows = [{"frame": 0, "rot_deg": 1.0, "trans_mm": 3.0, "depth_mm": -2.0, "status": "OK"},
            {"frame": 4, "rot_deg": 6.0, "trans_mm": 95.0, "depth_mm": 92.0, "status": "OK"},
            {"frame": 8, "rot_deg": 2.0, "trans_mm": 10.0, "depth_mm": 8.0, "status": "OK"}]
    s = eb.summary(rows)
    assert s["n"] == 3 and s["beyond"] == 1
    np.testing.assert_allclose([s["rot_mean"], s["rot_max"], s["trans_max"], s["depth_mean"], s["depth_abs_max"]],
                               [3.0, 6.0, 95.0, 98.0 / 3, 92.0])
    text = eb.report("cmd", ((0.0,) * 3, (0.0,) * 3), 60.0, {("truck", "lines"): rows},
                     {"truck": ("turntable-truck", 320, 240, 60, 0.0)}, 4)
    row = next(t for t in text.splitlines() if t.startswith("| truck | lines |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:] == ["3", "3.00", "6.00", "36.0", "95.0", "+32.7", "92.0", "1"]
    assert "4: 6.0 / +92" in text


def test_turntable_scores_m3t_results_like_its_own(tmp_path, monkeypatch):
    """experiments/turntable.py's M3T path without M3T: a stand-in runner writes the ground truth as its BOP results
    CSV (frames in reverse order, as a CSV may list them); the score is then exact (angle error 0, no failure), and the
    ms column is the CSV's time."""
    import dataclasses
    import textwrap

    from jaxtrack.io import read_sequence

    tt = _load("turntable")
    cfg = dataclasses.replace(tt.tp.preset_config("occluded-box", 0.15, 4), motion="turntable", occluders=0)
    seq = read_sequence(tt.tp.write_preset("occluded-box-turntable", cfg, tmp_path))
    runner = tmp_path / "m3t_stand_in.py"
    runner.write_text(textwrap.dedent(f"""\
        #!{sys.executable}
        import json, pathlib, sys
        seq, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[sys.argv.index("-o") + 1])
        gt = json.loads((seq / "000000" / "scene_gt.json").read_text())
        rows = ["scene_id,im_id,obj_id,score,R,t,time"]
        for im in sorted(gt, key=int, reverse=True):
            g = gt[im][0]
            R, t = " ".join(map(str, g["cam_R_m2c"])), " ".join(map(str, g["cam_t_m2c"]))
            rows.append(f"0,{{im}},{{g['obj_id']}},1,{{R}},{{t}},0.002")
        out.write_text("\\n".join(rows) + "\\n")
        """))
    runner.chmod(0o755)
    monkeypatch.setattr(tt.tp, "M3T_RUN", runner)
    r = tt.track_m3t_turntable(seq, "region", tmp_path)
    assert r["frames"] == 3 and r["first_failure"] is None and r["lost"] is None
    assert r["angle_err_mean"] < 1e-6 and r["rot_deg"] < 1e-3 and r["trans_mm"] < 1e-3
    assert abs(r["ms"] - 2.0) < 1e-9
    np.testing.assert_allclose(r["angle_est"], r["angle_true"], atol=1e-6)


def test_levelset_noise_scores_the_pixels_the_motion_moved_and_reads_its_settings():
    ln = _load("levelset_noise")
    prev = np.zeros((10, 12), bool)
    prev[2:6, 2:6] = True
    now = np.zeros((10, 12), bool)
    now[2:6, 4:8] = True  # moved 2 px right: 16 pixels changed
    phi = np.where(now[1:9, 1:11], 1.0, -1.0)  # a crop at (row 1, column 1) that follows the object
    assert ln.moved_pixels_right(phi, (1, 1), now, prev) == (16, 16)
    stuck = np.where(prev[1:9, 1:11], 1.0, -1.0)  # a segmentation left on the previous silhouette
    assert ln.moved_pixels_right(stuck, (1, 1), now, prev) == (16, 0)
    # A crop that reaches past the frame's border is cut, not wrapped: outside it nothing is object, which is
    # right for the 8 pixels the object left and wrong for the 8 it entered.
    assert ln.moved_pixels_right(np.ones((6, 6)), (7, 9), now, prev) == (16, 8)
    assert ln.parse_settings("0:1,1:0.3") == [(0.0, 1.0), (1.0, 0.3)]
    for bad in ("1", "3:1", "1:0", "a:b"):
        with pytest.raises(SystemExit, match="--settings|SIGMA"):
            ln.parse_settings(bad)


def test_profile_step_refuses_too_few_frames_and_tables_by_share(capsys):
    """experiments/profile_step.py: fewer than 3 frames stop with a message naming --frames (before any sequence is
    rendered); its tables list the largest first with their share of the total."""
    module = _load("profile_step")
    with pytest.raises(SystemExit):
        module.main(["--frames", "2"])
    assert "--frames must be ≥ 3" in capsys.readouterr().err
    import collections

    rows = module.table(collections.Counter({"a.py:f:1": 3e6, "b.py:g:2": 9e6}), 3, 5, 12e6)
    assert rows[2] == "| 3.00 | 75.0 % | `b.py:g:2` |" and rows[3] == "| 1.00 | 25.0 % | `a.py:f:1` |"


def test_warm_start_ab_reads_its_variants_and_pairs_the_rounds(tmp_path):
    """experiments/warm_start_ab.py: a variant without '=' or with a missing folder is refused naming it; the table's
    medians and the paired ratios come from the rounds as given, in the order of the variants."""
    ab = _load("warm_start_ab")
    with pytest.raises(SystemExit, match="LABEL=PYTHONPATH"):
        ab.parse_variant("no-equals-sign")
    with pytest.raises(SystemExit, match="does not exist"):
        ab.parse_variant(f"old={tmp_path / 'missing'}")
    assert ab.parse_variant(f" old ={tmp_path}") == ("old", str(tmp_path))
    assert ab.variant_env("") == {}
    assert ab.variant_env(str(tmp_path))["PYTHONPATH"].split(":")[0] == str(tmp_path)

    def run(ready):
        return {"ready_s": ready, "imported_s": ready / 2, "start_s": 0.5, "first_step_s": 0.5, "ml_dtypes": "x",
                "trimesh_imported": False, "jaxtrack_from": "/j"}

    warm = {("a", 1): [run(2.0), run(4.0), run(3.0)], ("b", 1): [run(1.0), run(3.0), run(1.5)]}
    cold = {("a", 1): run(30.0), ("b", 1): run(20.0)}

    class Args:
        title, cues, cold = "T", "all", False

    class Clock:
        load_start = (0.0, 0.0, 0.0)

        def elapsed_s(self):
            return 1.0

    text = ab.report(Args, "cmd", [("a", ""), ("b", "")], [1], cold, warm, Clock())
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in text.splitlines() if line.startswith(("| a ", "| b "))}
    assert rows["a"][3] == "3.00" and rows["b"][3] == "1.50"  # medians of the rounds
    assert "- b, 1 camera: [0.5, 0.75, 0.5]" in text
    assert "first frame, warm (s)" in text and "Cold fills" in text
    # --cold: every round from empty caches, no fill; the table says so and has no fill line.
    Args.cold, Args.title = True, None  # no --title: the title says which
    text = ab.report(Args, "cmd", [("a", ""), ("b", "")], [1], {}, warm, Clock())
    assert "first frame, cold (s)" in text and "empty compile" in text and "Cold fills" not in text
    assert text.startswith("# Cold first frame")
    assert "- b, 1 camera: [0.5, 0.75, 0.5]" in text


def test_energy_bias_one_step_mode_names_its_measure_and_file():
    """experiments/energy_bias.py --step 1: the report says it measures one step onto frame k+1 (not the bias), a
    negative step is refused naming the option, and the default output is one_step_1*.md."""
    eb = _load("energy_bias")
    rows = [{"frame": 0, "rot_deg": 6.0, "trans_mm": 4.7, "depth_mm": -4.5, "status": "OK"}]
    text = eb.report("cmd", ((0.0,) * 3, (0.0,) * 3), 60.0, {("truck", "lines"): rows},
                     {"truck": ("turntable-truck", 320, 240, 60, 0.0)}, 1, step=1)
    assert text.startswith("# One step from the true pose: frame k onto frame k+1")
    assert "`Tracker.step` on frame k+1, against the truth of frame k+1" in text and "0: 6.0 / -4" in text
    assert eb.report("cmd", ((0.0,) * 3, (0.0,) * 3), 60.0, {("truck", "lines"): rows},
                     {"truck": ("turntable-truck", 320, 240, 60, 0.0)}, 1).startswith("# Energy bias")
    with pytest.raises(SystemExit, match="--step must be ≥ 0"):
        eb.main(["--step", "-1"])


def test_view_model_build_refuses_unknown_meshes_and_tables_the_rounds(tmp_path, monkeypatch):
    """experiments/view_model_build.py: a mesh that is neither built in nor a file is refused naming --meshes; the
    table has each variant's median over the rounds and says whether the variants' models were identical."""
    vmb = _load("view_model_build")
    with pytest.raises(SystemExit, match="--meshes"):
        vmb.mesh_path("no-such-mesh")
    assert vmb.mesh_path("box") == "box"
    times = iter([3.0, 1.0, 5.0, 2.0, 4.0, 3.0])  # rounds alternate: a, b, a, b, a, b

    def fake_build(path, variant_path, out):
        np.savez(out, points=np.arange(4.0) + (1.0 if variant_path else 0.0))  # variant b's model differs
        return next(times), 12

    monkeypatch.setattr(vmb, "build_once", fake_build)
    out = tmp_path / "v.md"
    vmb.main(["--meshes", "box", "--rounds", "3", "--variant", "a=", "--variant", f"b={tmp_path}", "--out", str(out)])
    row = next(line for line in out.read_text().splitlines() if line.startswith("| box |")).split(" | ")
    assert row[1] == "12" and row[2].startswith("4.00 [3.0, 5.0, 4.0]") and row[3].startswith("2.00 [1.0, 2.0, 3.0]")
    assert row[4].strip(" |") == "no"
