"""Builds and executes notebooks/quickstart.ipynb (run: python notebooks/build_quickstart_notebook.py).

Reads the ViSP tea box (../shared/data/sequences/visp_teabox, first frames), jit-compiles the tracker,
tracks, plots the errors against the ground truth and shows overlay frames. `--smoke` (or
JAXTRACK_NOTEBOOK_SMOKE=1) uses the smoke configuration instead: a synthetic occluded box at 96x72,
region cue, 4 frames (the `tracker_quick` configuration of the experiments' smoke runs).
Needs the notebook extra: pip install -e ".[notebooks]".
"""

import sys

CELLS = [
    ("md", "# jaxtrack quickstart: read a sequence, jit the tracker, track, look at the errors\n\n"
           "The tracker of Brox, Rosenhahn, Gall and Cremers (TPAMI 2010) in JAX: per frame, optical flow and SIFT "
           "matches predict the pose, then level-set segmentation with the model's silhouette as shape prior, shape "
           "matching and a fused Gauss-Newton solve refine it. The whole per-frame step is one jitted function of "
           "arrays (`jaxtrack.track.track_step`); `Tracker` is its host edge (crops, SIFT detection, raster plans)."),
    ("code", "import os, pathlib, time, tempfile, dataclasses\nimport numpy as np, jax\nimport matplotlib.pyplot as plt\n"
             "import jaxtrack as jt\nfrom jaxtrack.io import read_sequence, load_mesh\n"
             "from jaxtrack.track import Tracker, TrackerConfig, pose_errors, track_sequence, overlay_frame\n"
             "SMOKE = os.environ.get('JAXTRACK_NOTEBOOK_SMOKE') == '1'\n"
             "ROOT = pathlib.Path(os.environ.get('JAXTRACK_ROOT', pathlib.Path.cwd().parent))\n"
             "print(jax.__version__, jax.devices(), 'smoke' if SMOKE else 'full')"),
    ("md", "## Read a sequence (BOP layout)\n\n"
           "The full notebook reads the first frames of the ViSP tea box (real video, 640x480, ground truth from "
           "ViSP's tracker); the smoke version writes a small synthetic sequence with `jaxtrack.synth` (exact ground "
           "truth, two moving occluders)."),
    ("code", "if SMOKE:\n"
             "    from jaxtrack.synth import PRESETS, write_sequence\n"
             "    base = PRESETS['occluded-box']\n"
             "    cfg = dataclasses.replace(base, width=96, height=72, focal=base.focal * 0.15, step_px=base.step_px * 0.15, frames=4)\n"
             "    path = write_sequence(cfg, pathlib.Path(tempfile.mkdtemp()) / 'occluded-box')\n"
             "    cues, frames = ('region',), 4\n"
             "else:\n"
             "    path = ROOT.parent / 'shared' / 'data' / 'sequences' / 'visp_teabox'\n"
             "    cues, frames = ('region', 'flow', 'sift'), 12\n"
             "seq = read_sequence(path)\nview = seq.views[0]\nobj_id = min(seq.model_paths)\n"
             "print(path.name, f'{view.width}x{view.height},', seq.num_frames, 'frames, object', obj_id, '-> tracking', frames,\n"
             "      'frames with cues', cues)\n"
             "fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))\n"
             "for a, k in zip(ax, (0, frames - 1)):\n"
             "    a.imshow(view.read_frame(k).astype(np.uint8)); a.set_title(f'frame {k}'); a.axis('off')"),
    ("md", "## Track\n\n"
           "`track_sequence` starts the tracker at the first frame's true pose and runs `Tracker.step` on every "
           "further frame. The first step traces and compiles the jitted step for this cue subset and crop size class "
           "(tens of seconds on a CPU); the other frames reuse it."),
    ("code", "times = []\nt0 = time.perf_counter()\n"
             "records = []\n"
             "run = track_sequence(seq, cues=cues, max_frames=frames, progress=False,\n"
             "                     on_frame=lambda r: (times.append(time.perf_counter()), records.append(r)))\n"
             "steps = np.diff(times)\n"
             "print(f'first step (incl. compile) {steps[0]:.1f} s, then median {np.median(steps[1:]):.2f} s per frame')\n"
             "print('statuses:', run.status)"),
    ("md", "## Errors against the ground truth (camera 0)"),
    ("code", "gt = view.T_cam_obj[obj_id][:frames]\nrot, trans = pose_errors(run.T_cam_obj(0), gt)\n"
             "fig, ax = plt.subplots(1, 2, figsize=(10, 3))\n"
             "ax[0].plot(rot, 'o-'); ax[0].set_ylabel('rotation error (°)'); ax[0].set_xlabel('frame')\n"
             "ax[1].plot(trans, 'o-'); ax[1].set_ylabel('translation error (mm)'); ax[1].set_xlabel('frame')\n"
             "print(f'mean over tracked frames: {np.mean(rot[1:]):.2f}° / {np.mean(trans[1:]):.2f} mm; '\n"
             "      f'5 cm / 5° success {np.mean((rot[1:] < 5) & (trans[1:] < 50)):.0%}')"),
    ("md", "## Overlay frames: model contour at the estimate (green), segmented contour (magenta)"),
    ("code", "mesh = load_mesh(seq.model_paths[obj_id])\nV = np.asarray(mesh.vertices, np.float64)\n"
             "show = [records[k] for k in sorted({1, len(records) // 2, len(records) - 1})]\n"
             "fig, ax = plt.subplots(1, len(show), figsize=(4.5 * len(show), 3.5))\n"
             "for a, r in zip(np.atleast_1d(ax), show):\n"
             "    p_cam = [V @ r.T_cam_obj[0][:3, :3].T + r.T_cam_obj[0][:3, 3]]\n"
             "    img = overlay_frame(r.images[:1], p_cam, np.asarray(mesh.faces), view.K[None], region_phi=r.region_phi,\n"
             "                        offsets=r.offsets, text=f'frame {r.index} {r.status}')\n"
             "    a.imshow(img); a.axis('off')"),
]


def main(argv=None):
    import os

    args = sys.argv[1:] if argv is None else argv
    if "--smoke" in args:
        os.environ["JAXTRACK_NOTEBOOK_SMOKE"] = "1"
    from _notebook import build

    build(CELLS, "quickstart.ipynb", timeout=1800)


if __name__ == "__main__":
    main()
