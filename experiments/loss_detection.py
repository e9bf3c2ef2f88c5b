"""Loss detection (issue 24): how well the tracker's per-frame evidence predicts a frame beyond 5 cm / 5°.

Every sequence is tracked from its first true pose without resets, with the tracker's defaults (lines, flow,
SIFT, occlusion detection). Per frame the evidence the step reports is kept:

- contour: 1 − the line modality's agreement (the fraction of its lines whose contour lies off the model's);
- motion: 1 − `motion_inliers` (flow / SIFT rows that disagree with the final pose);
- occluded: `occluded_fraction` (object pixels whose appearance disagrees with the model, eq. 9);
- appearance: `appearance_distance` (mean histogram distance d of eq. 9 over the known object pixels);
- jump_pred: the rotation (°/10) from the motion prediction to the final pose;
- and the running average of each of these over the frames so far (`*_avg`: a · average + (1 − a) · frame,
  a = `TrackerParams.loss_evidence_decay`, from zeros at the first frame): a pose that drifts off slowly shows weak
  evidence on many frames in a row.

Predictors of "beyond 5 cm / 5°" scored against the truth:

- before: the contour agreement below 0.8 (the rule before the calibrated confidence);
- status: the frame reported LOST or UNCERTAIN by the tracker (its calibrated confidence: the lower of two logistic
  models' p(right), `jaxtrack.track._step.LOSS_WEIGHTS`);
- refit: the same two models (one on the frame's evidence alone, one with the running averages) fitted by this run
  on *calibration* sequences (other seeds, objects and motions than the evaluation ones, plus pose jumps injected
  into the state), the larger p(fail) > 0.5, applied unchanged to the *evaluation* sequences: the frame-rate
  experiment's sequences at S = 2..4, the occluded-box preset and the teapot turntable, as issue 24 names them.

    python experiments/loss_detection.py          # experiments/results/loss_detection.md / .png / .json
    python experiments/loss_detection.py --quick --out /tmp/l.md   # smoke run (2 short sequences each)
    python experiments/loss_detection.py --analyse experiments/results/loss_detection.json \
        --out experiments/results/loss_detection_decay.md   # no tracking: the averages' decay, the frame's model
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import shutil
import sys
import tempfile

import numpy as np
import track_presets as tp

from jaxtrack.bench import command_line, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
from jaxtrack.track._step import LOSS_EVIDENCE as FEATURES
from jaxtrack.track._step import LOSS_FRAME_EVIDENCE, LOSS_WEIGHTS

MAX_DEG, MAX_MM = 5.0, 50.0


# --- sequences -------------------------------------------------------------------------------------------
def evaluation_configs(scale: float, frames: int, quick: bool) -> list[tuple[str, object]]:
    """The sequences issue 24 names: frame-rate variants at S = 2..4, the occluded preset, the teapot turntable."""
    from jaxtrack.synth import PRESETS

    out = []
    base = tp.preset_config("occluded-box", scale, None)
    base = dataclasses.replace(base, frames=frames, step_px=10.0 * scale, step_deg=3.0)
    steps = (4,) if quick else (2, 3, 4)
    for variant in ("regular",) if quick else ("regular", "noisy", "occluded"):
        v = dataclasses.replace(base, noise_sigma=40.0 if variant == "noisy" else 0.0, occluders=2 if variant == "occluded" else 0)
        for s in steps:
            out.append((f"frame-rate {variant} S={s}", dataclasses.replace(
                v, frames=frames // s, subsample=s, step_px=v.step_px * s, step_deg=v.step_deg * s)))
    if not quick:
        out.append(("occluded-box", tp.preset_config("occluded-box", scale, None)))
        teapot = PRESETS["turntable-teapot"]
        out.append(("turntable-teapot", dataclasses.replace(tp.preset_config("turntable-teapot", scale, None),
                                                            frames=teapot.frames)))
    return out


CALIBRATION_OBJECTS = (  # (object, appearance, texture photo, background)
    ("box", "photo", "astronaut", "coffee"),
    ("cracker_box", "texture", "astronaut", "brick"),
    ("milk_truck", "texture", "astronaut", "grass"),
    ("teapot", "flat", "astronaut", "gravel"),
)


def calibration_configs(scale: float, frames: int, quick: bool, seeds: int) -> list[tuple[str, object]]:
    """Other seeds (1..), objects, backgrounds and motions than the evaluation: regular, noisy and occluded
    variants at 2 and 4 times the base motion."""
    from jaxtrack.synth import SynthConfig

    out = []
    objects = CALIBRATION_OBJECTS[:1] if quick else CALIBRATION_OBJECTS
    for seed in range(1, 1 + seeds):
        for obj, look, photo, background in objects:
            for variant in ("regular",) if quick else ("regular", "noisy", "occluded"):
                for mult in (2,) if quick else (2, 4):
                    cfg = SynthConfig(object=obj, appearance=look, texture_photo=photo, background=background,
                                      motion="random", step_px=5.0 * mult, step_deg=2.0 * mult, frames=frames,
                                      noise_sigma=40.0 if variant == "noisy" else 0.0,
                                      occluders=2 if variant == "occluded" else 0, seed=seed,
                                      width=round(640 * scale), height=round(480 * scale), focal=700.0 * scale,
                                      colour=(210, 180, 60))
                    out.append((f"{obj} {variant} x{mult} seed {seed}", cfg))
    return out


# --- tracking ----------------------------------------------------------------------------------------------
def track(seq, inject_at: int | None = None, inject_deg: float = 0.0, seed: int = 0) -> list[dict]:
    """Track camera 0 of `seq` without resets; one feature row per frame 1.. (with the truth's errors).

    `inject_at`: before that frame the state's pose is turned by `inject_deg` about a random axis (a pose
    jump the tracker did not make: a positive example of a lost frame for the calibration)."""
    import equinox as eqx
    import jax.numpy as jnp

    from jaxtrack.geometry import make_camera, rotation_error_deg, so3_exp, stack_cameras
    from jaxtrack.io import load_mesh
    from jaxtrack.track import Tracker, TrackerConfig, success_mask

    view = seq.views[0]
    rig = stack_cameras([make_camera(view.K, view.width, view.height, view.T_cam_world[:3, :3], view.T_cam_world[:3, 3])])
    oid = min(seq.model_paths)
    T_world = np.einsum("ij,fjk->fik", np.linalg.inv(np.asarray(view.T_cam_world, np.float64)), view.T_cam_obj[oid])
    # The status's evidence on the frames as tracked, without the search after a LOST frame (`recovery` None).
    tracker = Tracker(load_mesh(seq.model_paths[oid]), rig, config=TrackerConfig(recovery=None))
    state = tracker.start(view.read_frame(0)[None], T_world[0])
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(1, seq.num_frames):
        if inject_at is not None and k == inject_at:
            axis = rng.normal(size=3)
            T = np.asarray(state.T_world_root, np.float64)
            T_new = T.copy()  # turned about the object's own centre
            T_new[:3, :3] = T[:3, :3] @ np.asarray(so3_exp(jnp.asarray(axis / np.linalg.norm(axis) * np.radians(inject_deg))))
            state = eqx.tree_at(lambda s: s.T_world_root, state, jnp.asarray(T_new, tracker.dtype))
        state, r, _ = tracker.step(state, view.read_frame(k)[None])
        T = np.asarray(r.T_world_root, np.float64)
        rot = float(rotation_error_deg(T[:3, :3], T_world[k][:3, :3]))
        trans = float(np.linalg.norm(T[:3, 3] - T_world[k][:3, 3]))
        evidence = np.asarray(r.loss_evidence, np.float64)
        rows.append({
            "frame": k, "rot_deg": rot, "trans_mm": trans, "failed": not bool(success_mask(rot, trans, MAX_DEG, MAX_MM)),
            "status": int(r.status), "confidence": float(r.confidence), "injected": inject_at == k,
            **{name: float(v) for name, v in zip(FEATURES, evidence, strict=True)},
        })
    return rows


# --- the calibrated predictor ---------------------------------------------------------------------------------
def design(rows: list[dict]) -> np.ndarray:
    return np.array([[1.0] + [r[f] for f in FEATURES] for r in rows])


def fit_logistic(X: np.ndarray, y: np.ndarray, l2: float = 1e-2, iters: int = 50) -> np.ndarray:
    """Newton / IRLS for the L2-regularised logistic regression (the intercept not penalised)."""
    w = np.zeros(X.shape[1])
    reg = l2 * np.eye(X.shape[1])
    reg[0, 0] = 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-np.clip(X @ w, -30, 30)))
        g = X.T @ (p - y) + reg @ w
        H = (X * (p * (1 - p))[:, None]).T @ X + reg
        step = np.linalg.solve(H, g)
        w -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    return w


def fit_models(rows: list[dict]) -> np.ndarray:
    """(2, 1 + len(FEATURES)) the tracker's two models fitted on `rows`: row 0 on the frame's own evidence alone (zero
    weights on the running averages), row 1 on all of it (`jaxtrack.track._step.LOSS_WEIGHTS`' layout)."""
    X = design(rows)
    y = np.array([r["failed"] for r in rows], float)
    n = 1 + len(LOSS_FRAME_EVIDENCE)
    frame = np.zeros(X.shape[1])
    frame[:n] = fit_logistic(X[:, :n], y)
    return np.stack([frame, fit_logistic(X, y)])


def probability(w: np.ndarray, rows: list[dict]) -> np.ndarray:
    """p(fail) per row of `rows`: the largest of the models' (rows of `w`; the tracker's confidence is the least
    p(right))."""
    logits = design(rows) @ np.atleast_2d(w).T
    return np.max(1.0 / (1.0 + np.exp(-np.clip(logits, -30, 30))), axis=1)


# --- report -------------------------------------------------------------------------------------------------
def _f(x, digits=2) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _pr_cells(flag, y) -> str:
    from jaxtrack.track import precision_recall

    p, r = precision_recall(flag, y)
    return f"{_f(p)} | {_f(r)}"


# --- re-analysis of a saved run (--analyse): the averages' decay, chosen on the calibration sequences -------------
DECAYS = (0.3, 0.5, 0.6, 0.7, 0.8, 0.9)
FOLDS = 6


def with_averages(groups: list, decay: float) -> list:
    """The saved rows with the `*_avg` features recomputed from their frame evidence for another decay (from zeros,
    as the tracker: a · average + (1 − a) · frame)."""
    out = []
    for name, rows in groups:
        average = np.zeros(len(LOSS_FRAME_EVIDENCE))
        new_rows = []
        for r in rows:
            frame = np.array([r[f] for f in LOSS_FRAME_EVIDENCE])
            average = decay * average + (1.0 - decay) * frame
            new_rows.append({**r, **{f"{f}_avg": float(v) for f, v in zip(LOSS_FRAME_EVIDENCE, average, strict=True)}})
        out.append((name, new_rows))
    return out


def cross_validated(groups: list, columns: int) -> tuple[float, np.ndarray, np.ndarray]:
    """(mean log-loss, p(fail), failed) of one logistic model on the first `columns` of the design, each sequence
    predicted by the fit on the other folds (sequence i in fold i % FOLDS)."""
    losses, probs, ys = [], [], []
    for fold in range(FOLDS):
        train = [r for i, (_, rs) in enumerate(groups) if i % FOLDS != fold for r in rs]
        test = [r for i, (_, rs) in enumerate(groups) if i % FOLDS == fold for r in rs]
        if not test:
            continue
        w = fit_logistic(design(train)[:, :columns], np.array([r["failed"] for r in train], float))
        p = np.clip(1.0 / (1.0 + np.exp(-np.clip(design(test)[:, :columns] @ w, -30, 30))), 1e-6, 1 - 1e-6)
        y = np.array([r["failed"] for r in test], float)
        losses.append(-(y * np.log(p) + (1 - y) * np.log(1 - p)))
        probs.append(p)
        ys.append(y > 0)
    return float(np.mean(np.concatenate(losses))), np.concatenate(probs), np.concatenate(ys)


def analyse(saved: dict, command: str) -> str:
    """The table behind the decay and the two models: for each decay, the calibration sequences' cross-validated
    log-loss and P / R of the model with the averages (the choice), and its fit's P / R on the evaluation sequences
    (shown, not used); the frame's model alone; and the best that model could do on the evaluation sequences with
    a threshold chosen on them (an upper bound)."""
    from jaxtrack.track import precision_recall

    if list(saved["features"]) != list(FEATURES):
        raise SystemExit(f"--analyse: the run's features {saved['features']} are not this code's {list(FEATURES)}")
    n = 1 + len(LOSS_FRAME_EVIDENCE)
    cells = lambda p, y: " | ".join(_f(v) for v in precision_recall(p > 0.5, y))
    lines = ["# Loss detection: the running averages' decay and the frame's evidence alone", "",
             f"Command: `{command}` (a re-analysis of a saved run of this script: no tracking).", "",
             (f"Calibration sequences: {len(saved['calibration'])}; each decay's averages recomputed from the saved frame "
              f"evidence (from zeros, as the tracker). Cross-validation: {FOLDS} folds over the calibration sequences "
              "(sequence i in fold i mod 6). The decay is chosen on the calibration log-loss; the evaluation columns are "
              "shown, not used."), "",
             "| model | calibration CV log-loss | calibration CV P | calibration CV R | evaluation P | evaluation R |",
             "|---|---:|---:|---:|---:|---:|"]
    rows_e = [r for _, rs in saved["evaluation"] for r in rs]
    y_e = np.array([r["failed"] for r in rows_e])
    loss, p, y = cross_validated(saved["calibration"], n)
    w = fit_logistic(design([r for _, rs in saved["calibration"] for r in rs])[:, :n],
                     np.array([r["failed"] for _, rs in saved["calibration"] for r in rs], float))
    p_frame = 1.0 / (1.0 + np.exp(-np.clip(design(rows_e)[:, :n] @ w, -30, 30)))
    lines.append(f"| the frame alone | {loss:.3f} | {cells(p, y)} | {cells(p_frame, y_e)} |")
    for decay in DECAYS:
        calib = with_averages(saved["calibration"], decay)
        loss, p, y = cross_validated(calib, 1 + len(FEATURES))
        w = fit_logistic(design([r for _, rs in calib for r in rs]), np.array([r["failed"] for _, rs in calib for r in rs], float))
        evals = [r for _, rs in with_averages(saved["evaluation"], decay) for r in rs]
        p_e = 1.0 / (1.0 + np.exp(-np.clip(design(evals) @ w, -30, 30)))
        lines.append(f"| with the averages, a = {decay} | {loss:.3f} | {cells(p, y)} | {cells(p_e, y_e)} |")
    best = max((min(precision_recall(p_frame > t, y_e)), t) for t in np.linspace(0.01, 0.99, 99))
    lines += ["", (f"The frame's model alone (fitted on all calibration sequences) on the evaluation sequences with the "
                   f"threshold on p(fail) that maximises min(P, R) there: min(P, R) = {best[0]:.2f} at {best[1]:.2f} "
                   "(an upper bound: the threshold is chosen on the sequences it is scored on).")]
    return "\n".join(lines) + "\n"


MODEL_NAMES = ("the frame alone", "with the running averages")


def report(command, elapsed_s, load, calib, evals, w) -> str:
    from jaxtrack._status import Status

    start, end = (tuple(round(x, 2) for x in v) for v in load)
    machine = f"Machine: 2-core CPU; load average (1, 5, 15 min) at the start {start}, at the end {end}; run took {elapsed_s / 60:.1f} min."
    flagged = lambda rows: np.array([r["status"] in (Status.LOST, Status.UNCERTAIN) for r in rows])
    lost = lambda rows: np.array([r["status"] == Status.LOST for r in rows])
    before = lambda rows: np.array([1.0 - r["contour"] < 0.8 for r in rows])  # the old rule: agreement < uncertain_iou
    refit = lambda rows: probability(w, rows) > 0.5
    lines = ["# Loss detection: does the per-frame evidence predict a frame beyond 5 cm / 5°?", "",
             f"Command: `{command}`  ", machine, "",
             ("Tracked without resets from the first true pose with the tracker's defaults (lines + flow + SIFT, "
             "occlusion detection, 96x128 working resolution), camera 0. A frame *fails* beyond 5 cm or 5°. "
             "Predictors of a failed frame (precision P, recall R):"),
             "- *before*: the rule up to now, the contour agreement below 0.8 (`uncertain_iou`: UNCERTAIN or LOST);",
             ("- *status*: the tracker's status now, LOST or UNCERTAIN, from its calibrated confidence "
             "min_k 1 − σ(w_k · [1, `FrameResult.loss_evidence`]) with the models in `jaxtrack.track._step.LOSS_WEIGHTS` "
             "(UNCERTAIN below 0.5, LOST below 0.25); *LOST*: that status alone;"),
             ("- *refit*: the same models fitted by this run on its calibration sequences (one on the frame's own "
              "evidence, one with the running averages), the larger p(fail) > 0.5 (equal to *status* when the weights "
              "in the code are this run's)."), "",
             "## Evaluation sequences (not seen by the calibration)", "",
             "| sequence | frames | failed | flagged (status) | before P | before R | status P | status R | LOST P | LOST R | refit P | refit R |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    all_rows = []
    for name, rows in evals:
        y = np.array([r["failed"] for r in rows])
        lines.append(f"| {name} | {len(rows)} | {int(y.sum())} | {int(flagged(rows).sum())} | {_pr_cells(before(rows), y)} | {_pr_cells(flagged(rows), y)} | "
                     f"{_pr_cells(lost(rows), y)} | {_pr_cells(refit(rows), y)} |")
        all_rows += rows
    y = np.array([r["failed"] for r in all_rows])
    lines.append(f"| **all** | {len(all_rows)} | {int(y.sum())} | {int(flagged(all_rows).sum())} | {_pr_cells(before(all_rows), y)} | "
                 f"{_pr_cells(flagged(all_rows), y)} | {_pr_cells(lost(all_rows), y)} | {_pr_cells(refit(all_rows), y)} |")
    rows_c = [r for _, rs in calib for r in rs]
    yc = np.array([r["failed"] for r in rows_c])
    tracker_w = np.atleast_2d(np.asarray(LOSS_WEIGHTS, np.float64))
    same = [k < len(tracker_w) and np.allclose(w[k], tracker_w[k], atol=5e-3) for k in range(len(w))]
    lines += ["", "Goal (issue 24): precision and recall ≥ 0.9 on these sequences.", "",
              "## The calibrated combination", "",
              (f"Fitted on {len(calib)} calibration sequences ({len(rows_c)} frames, {int(yc.sum())} failed; pose jumps "
               f"of 20-60° injected into every other one), refit P | R on them: {_pr_cells(refit(rows_c), yc)}."), "",
              "| weights | " + " | ".join(("intercept", *FEATURES)) + " |", "|---|" + "---:|" * (len(FEATURES) + 1),
              *(f"| this run's fit, {MODEL_NAMES[k]} | " + " | ".join(f"{v:.3f}" for v in w[k]) + " |" for k in range(len(w))),
              *(f"| the tracker's (`LOSS_WEIGHTS[{k}]`), {MODEL_NAMES[k]} | " + " | ".join(f"{v:.3f}" for v in tracker_w[k]) + " |"
                for k in range(len(tracker_w))), "",
              *(f"The tracker's model {k} ({MODEL_NAMES[k]}) {'is' if same[k] else 'is not'} this run's fit." for k in range(len(w))), "",
              ("Each of this run's fits alone and the larger p(fail) of the two, on the evaluation sequences (P | R of "
               "p(fail) > 0.5 | of p(fail) > 0.75, LOST's bound):"), "",
              "| model | flagged P | flagged R | LOST P | LOST R |", "|---|---:|---:|---:|---:|",
              *(f"| {label} | {_pr_cells(probability(wk, all_rows) > 0.5, y)} | {_pr_cells(probability(wk, all_rows) > 0.75, y)} |"
                for label, wk in ((MODEL_NAMES[0], w[0]), (MODEL_NAMES[1], w[1]), ("the larger of the two", w))), "",
              "Mean evidence on the evaluation frames, tracked / failed:", "",
              "| evidence | tracked | failed |", "|---|---:|---:|"]
    for f in FEATURES:
        a = np.array([r[f] for r in all_rows])
        lines.append(f"| {f} | {_f(a[~y].mean() if (~y).any() else None, 3)} | {_f(a[y].mean() if y.any() else None, 3)} |")
    return "\n".join(lines) + "\n"


def plot(path, evals) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for _, rs in evals for r in rs]
    err = np.array([max(r["rot_deg"] / MAX_DEG, r["trans_mm"] / MAX_MM) for r in rows])
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].scatter(err, [1.0 - r["contour"] for r in rows], s=8)
    ax[0].set(xscale="log", xlabel="error / (5°, 5 cm) (max of the two)", ylabel="contour agreement", title="before (the contour)")
    ax[1].scatter(err, [r["confidence"] for r in rows], s=8, color="C1")
    ax[1].set(xscale="log", xlabel="error / (5°, 5 cm) (max of the two)", ylabel="FrameResult.confidence", title="calibrated")
    for a in ax:
        a.axvline(1.0, color="k", lw=0.8, ls="--")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=0.5, help="image scale (1 = 640x480)")
    ap.add_argument("--frames", type=int, default=36, help="frames of the frame-rate sequences at S = 1")
    ap.add_argument("--calibration-frames", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=1, help="calibration seeds per object and variant")
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 short sequences each")
    ap.add_argument("--seq-dir", default=None)
    ap.add_argument("--out", default=str(RESULTS / "loss_detection.md"))
    ap.add_argument("--analyse", default=None, metavar="JSON",
                    help="no tracking: re-analyse a saved run (its .json) for the averages' decay and the frame's model "
                         "alone; writes --out")
    args = ap.parse_args(argv)
    if args.analyse:
        path = pathlib.Path(args.analyse)
        if not path.is_file():
            raise SystemExit(f"--analyse: no file {path}")
        text = analyse(json.loads(path.read_text()), command_line(__file__, argv))
        print(text)
        pathlib.Path(args.out).write_text(text)
        return None
    if args.quick:
        args.frames, args.calibration_frames = 8, 6
    command = command_line(__file__, argv)

    from jaxtrack.io import read_sequence

    clock = start_experiment(cache=False)
    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="loss_"))
    try:
        calib = []
        for i, (name, cfg) in enumerate(calibration_configs(args.scale, args.calibration_frames, args.quick, args.seeds)):
            seq = read_sequence(tp.write_preset(f"calib{i}", cfg, seq_dir))
            inject = (seq.num_frames // 2, 20.0 + 40.0 * ((i * 7) % 5) / 4) if i % 2 == 0 else (None, 0.0)
            calib.append((name, track(seq, inject[0], inject[1], seed=i)))
            print(f"[loss_detection] calibration {name}: {sum(r['failed'] for r in calib[-1][1])}/{len(calib[-1][1])} failed "
                  f"({clock.minutes():.1f} min)", file=sys.stderr, flush=True)
        w = fit_models([r for _, rs in calib for r in rs])
        evals = []
        for i, (name, cfg) in enumerate(evaluation_configs(args.scale, args.frames, args.quick)):
            seq = read_sequence(tp.write_preset(f"eval{i}", cfg, seq_dir))
            evals.append((name, track(seq)))
            print(f"[loss_detection] evaluation {name}: {sum(r['failed'] for r in evals[-1][1])}/{len(evals[-1][1])} failed "
                  f"({clock.minutes():.1f} min)", file=sys.stderr, flush=True)
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    text = report(command, clock.elapsed_s(), (clock.load_start, os.getloadavg()), calib, evals, w)
    print(text)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps({"features": FEATURES, "weights": w.tolist(),
                                                    "calibration": calib, "evaluation": evals}))
    plot(out.with_suffix(".png"), evals)
    return w


if __name__ == "__main__":
    main()
