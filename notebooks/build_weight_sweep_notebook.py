"""Builds and executes notebooks/weight_sweep.ipynb (run: python notebooks/build_weight_sweep_notebook.py).

The cue-weight sweep of experiment 7 (`jax.vmap` of the per-frame step over tracker states and
weight factors) recomputed small, the full sweep's heat map and the learned weights of experiment 8
loaded from experiments/results. `--smoke` (or JAXTRACK_NOTEBOOK_SMOKE=1) recomputes on the smoke
configuration (occluded box 96x72, region cue, 4 frames, 2x2 grid).
Needs the notebook extra: pip install -e ".[notebooks]".
"""

import sys

CELLS = [
    ("md", "# jaxtrack cue-weight sweep: many weight settings tracked at once with `vmap`\n\n"
           "The method fuses contour, flow and SIFT correspondences with adaptive weights (Section V: flow "
           "w_i = c_i·n_C/n_OF, SIFT w = 0.002·n_C). User factors multiply them (`TrackerParams.weights`), and because "
           "every parameter is an array, `jax.vmap(track_step)` tracks a whole grid of factor settings in one compiled "
           "call per frame, each setting with its own tracker state. Does the method's adaptive weighting sit near "
           "the optimum?"),
    ("code", "import os, sys, json, pathlib, time, tempfile\nimport numpy as np, jax\nimport matplotlib.pyplot as plt\n"
             "SMOKE = os.environ.get('JAXTRACK_NOTEBOOK_SMOKE') == '1'\n"
             "ROOT = pathlib.Path(os.environ.get('JAXTRACK_ROOT', pathlib.Path.cwd().parent))\n"
             "sys.path.insert(0, str(ROOT / 'experiments'))\nimport weight_sweep as ws\n"
             "from track_presets import preset_config, write_preset\nfrom jaxtrack.io import read_sequence\n"
             "print(jax.__version__, jax.devices(), 'smoke' if SMOKE else 'full')"),
    ("md", "## A small sweep, recomputed here\n\n"
           "Per frame, the host picks each setting's crop (one shared size class) and its SIFT matches; one call of "
           "the vmapped step tracks every setting; a setting beyond 5 cm / 5° restarts from the true pose (RBOT)."),
    ("code", "if SMOKE:\n"
             "    preset, scale, frames, cues, flows, sifts = 'occluded-box', 0.15, 4, ('region',), (0.1, 1.0), (1.0, 10.0)\n"
             "else:\n"
             "    preset, scale, frames, cues, flows, sifts = 'noisy-moving-camera', 0.25, 6, ('region', 'flow', 'sift'), (0.1, 1.0), (1.0, 10.0)\n"
             "cfg = preset_config(preset, scale, frames)\nseq = read_sequence(write_preset(preset, cfg, pathlib.Path(tempfile.mkdtemp())))\n"
             "problem = ws.Problem(seq, cues, frames)\n"
             "grid_f = np.array([f for _ in sifts for f in flows]); grid_s = np.array([s for s in sifts for _ in flows])\n"
             "t = time.perf_counter()\nrun = ws.track_batch(problem, grid_f, grid_s, reset=True)\n"
             "print(f'{len(grid_f)} settings, {frames - 1} frames of {cfg.width}x{cfg.height} in {time.perf_counter() - t:.1f} s '\n"
             "      f'(first batched step incl. compile {run[\"step_s\"][0]:.1f} s)')\n"
             "scores = ws.summarise(run)\n"
             "for f, s, r in zip(grid_f, grid_s, scores):\n"
             "    print(f'flow {f:g}, SIFT {s:g}: success {r[\"success\"]:.0%}, mean rot {r[\"rot_deg\"]:.2f}°, trans {r[\"trans_mm\"]:.1f} mm')\n"
             "small = np.array([r['rot_deg'] for r in scores]).reshape(len(sifts), len(flows))"),
    ("md", "## The full sweep (experiment 7) and the learned weights (experiment 8)\n\n"
           "Loaded from `experiments/results/weight_sweep.json` and `learn_weights.json` (run "
           "`python experiments/weight_sweep.py` and `python experiments/learn_weights.py` to recompute)."),
    ("code", "sweep_file = ROOT / 'experiments' / 'results' / 'weight_sweep.json'\n"
             "learn_file = ROOT / 'experiments' / 'results' / 'learn_weights.json'\n"
             "if sweep_file.is_file():\n"
             "    data = json.loads(sweep_file.read_text())\n"
             "    flows, sifts = np.array(data['flow']), np.array(data['sift'])\n"
             "    rot = np.array([[c['rot_deg'] for c in row] for row in data['scores']])\n"
             "    fig, ax = plt.subplots(figsize=(6, 4.5))\n"
             "    im = ax.imshow(rot, origin='lower', cmap='viridis_r', aspect='auto')\n"
             "    for i in range(len(sifts)):\n"
             "        for j in range(len(flows)):\n"
             "            ax.text(j, i, f'{rot[i, j]:.1f}', ha='center', va='center', color='w', fontsize=8)\n"
             "    ax.set_xticks(range(len(flows)), [f'{f:g}' for f in flows]); ax.set_yticks(range(len(sifts)), [f'{s:g}' for s in sifts])\n"
             "    pos = lambda v, grid: float(np.interp(np.log(v), np.log(grid), np.arange(len(grid))))\n"
             "    ax.plot(pos(0.1, flows), pos(1.0, sifts), 'r*', ms=16, mfc='none', mew=2, label='tracker default (0.1, 1)')\n"
             "    ax.plot(pos(1.0, flows), pos(1.0, sifts), 'ro', ms=14, mfc='none', mew=2, label='paper (1, 1)')\n"
             "    if learn_file.is_file():\n"
             "        lf, ls = json.loads(learn_file.read_text())['learned']\n"
             "        ax.plot(pos(lf, flows), pos(ls, sifts), 'wD', ms=10, mfc='none', mew=2, label=f'learned ({lf:.3g}, {ls:.3g})')\n"
             "    ax.set_xlabel('flow weight factor'); ax.set_ylabel('SIFT weight factor'); ax.legend(fontsize=7, loc='upper left')\n"
             "    ax.set_title(f\"mean rotation error (°), {data['preset']} {data['width']}x{data['height']}, {data['frames']} frames\", fontsize=9)\n"
             "    fig.colorbar(im)\n"
             "else:\n"
             "    print('experiments/results/weight_sweep.json not found: run python experiments/weight_sweep.py')"),
    ("code", "if learn_file.is_file():\n"
             "    learn = json.loads(learn_file.read_text())\n"
             "    for h in learn['history']:\n"
             "        print(f\"flow {h['flow']:.4g}  SIFT {h['sift']:.4g}  training loss {h['loss']:.5g}\")\n"
             "    for seq_name, rows in learn['evals'].items():\n"
             "        for name, r in rows.items():\n"
             "            print(f\"{seq_name:32s} {name:22s} success {r['success']:.0%}  rot {r['rot_deg']:.2f}°  trans {r['trans_mm']:.1f} mm\")\n"
             "else:\n"
             "    print('experiments/results/learn_weights.json not found: run python experiments/learn_weights.py')"),
]


def main(argv=None):
    import os

    args = sys.argv[1:] if argv is None else argv
    if "--smoke" in args:
        os.environ["JAXTRACK_NOTEBOOK_SMOKE"] = "1"
    from _notebook import build

    build(CELLS, "weight_sweep.ipynb", timeout=1800)


if __name__ == "__main__":
    main()
